"""An independent accuracy reference: planar hinge trees by Lagrange's equations and scipy.

Used by the tests (``tests/planar_chain.py`` re-exports it) and by the experiments
(``experiments/default_calibration.py``: data from a simulator that shares no code with
treeinfer's MuJoCo/fused step).

Written from the equations of motion, not from MuJoCo, so that it can judge the simulator's
discretisation (step size, force interpolation), not just its agreement with MuJoCo.

Model (the same physics :mod:`treeinfer.tree.description` describes). Every branch ``b`` is a
uniform solid cylinder of mass ``m_b = rho pi r_b^2 L_b`` whose centre of mass lies at ``L_b / 2``
along its axis and whose moment of inertia about an axis through that centre, perpendicular to the
branch, is ``I_b = m_b (3 r_b^2 + L_b^2) / 12``
(:func:`treeinfer.tree.description.cylinder_inertia`). When every branch forks in the base's bending
plane (``azimuth_deg == 0``) and gravity lies in that plane, the motion is planar: each branch is
described by its *elevation* ``phi_b`` above the horizontal direction ``h = (cos yaw, sin yaw, 0)``
of the plane, with

    e(phi) = cos(phi) h + sin(phi) z          (unit vector along the branch)
    phi_b  = phi0_b - sum_{d in dofs(b)} q_d   (q: hinge angles, positive = downward)

where ``phi0_b = pitch + sum of the fork angles on the path`` and ``dofs(b)`` are the hinges of
``b`` and its ancestors (welded branches have none). Every point of the tree is
``base + sum_a R[a] e(phi_a)`` for coefficients ``R`` over ``a`` on the path from the root:
``attach * L_a`` for ancestors (the distance to the next fork on the path) and the point's own
distance along its branch (``L_b / 2`` for a centre of mass, ``f L_g`` for the grasp point).

Kinetic energy ``T = 1/2 phidot^T M(phi) phidot`` with
``M_ac = A_ac cos(phi_a - phi_c) + delta_ac I_a`` and ``A_ac = sum_b m_b R_b[a] R_b[c]``. Lagrange's
equations in the elevations are ``M phiddot + hvec = Q`` with the centrifugal terms
``hvec_a = sum_c A_ac sin(phi_a - phi_c) phidot_c^2`` and the generalised forces of gravity
``g`` and of the point force ``F`` at the grasp point C:
``Q_a = (sum_b m_b R_b[a] g + R_C[a] F) . e'(phi_a)``, ``e'(phi) = d e / d phi``. With
``phi = phi0 - S q`` (``S[b, d] = 1`` when hinge d moves branch b) the joint-space equations are

    S^T M S qddot = S^T (hvec - Q) + tau,   tau_d = -Kp_d q_d - Kd_d qdot_d

(a spring about the geometric rest angle and a damper, as in the tree's joints). The rest pose
is the static solution of ``S^T (-Q_gravity(q)) - Kp q = 0`` (``scipy.optimize.root``) and the
displacement is that of treeinfer: ``tau(t) = (C(t) - C_rest) . d`` along the unit pull
direction ``d`` (gravity's by default).

The force between samples is the piecewise-linear interpolation of the samples (``"linear"``) or
held from each sample to the next (``"hold"``), constant at the last sample after it. The
integration (``scipy.integrate.solve_ivp``, DOP853, rtol 1e-11) restarts at every kink of that
force signal so that the adaptive steps never straddle one.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import root

from treeinfer.tree.description import Tree, branch_density, cylinder_inertia


class PlanarTree:
    """The planar Lagrangian model of ``tree`` at given gains.

    Args:
      tree: a tree whose branches all have ``azimuth_deg == 0`` and gravity in the base plane.
      kp, kd: [R] gains of ``tree.inferred`` (N m/rad, N m s/rad); other hinges take
        ``tree.fixed_gains``.
      grasp_fraction: where on the grasped branch the force acts (None: the tree's).
      grasp_branch: which branch is grasped (None: the tree's).
      direction: [3] world pull direction (None: along gravity); must lie in the plane.
    """

    def __init__(self, tree: Tree, kp, kd, grasp_fraction=None, grasp_branch=None, direction=None):
        names = list(tree.names)
        for b in tree.branches:
            if b.azimuth_deg != 0.0 or b.twist_deg != 0.0:
                raise ValueError(
                    f"branch {b.name}: azimuth_deg and twist_deg must be 0 for a planar model"
                )
            if b.lump is not None:
                raise ValueError(f"branch {b.name}: welded lumps are not in the planar model")
        yaw = math.radians(tree.base_yaw_deg)
        self.h = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        self.z = np.array([0.0, 0.0, 1.0])
        normal = np.cross(self.z, self.h)
        self.g = np.asarray(tree.gravity, float)
        if abs(self.g @ normal) > 1e-12:
            raise ValueError("gravity must lie in the bending plane")
        d = self.g if direction is None else np.asarray(direction, float)
        self.direction = d / np.linalg.norm(d)
        if abs(self.direction @ normal) > 1e-12:
            raise ValueError("the pull direction must lie in the bending plane")
        self.base = np.asarray(tree.base_position, float)

        nb = len(names)
        idx = {n: i for i, n in enumerate(names)}
        parent = [idx[b.parent] if b.parent is not None else -1 for b in tree.branches]
        dof_branches = [i for i, b in enumerate(tree.branches) if not b.fixed]
        self.nv = len(dof_branches)
        dof_of = {b: d for d, b in enumerate(dof_branches)}
        self.phi0 = np.zeros(nb)
        self.S = np.zeros((nb, self.nv))
        for i, b in enumerate(tree.branches):
            p = parent[i]
            self.phi0[i] = math.radians(tree.base_pitch_deg if p < 0 else 0.0) + math.radians(
                b.angle_deg
            )
            if p >= 0:
                self.phi0[i] += self.phi0[p]
                self.S[i] = self.S[p]
            if i in dof_of:
                self.S[i, dof_of[i]] = 1.0

        def path_coeffs(i: int, own: float) -> np.ndarray:
            """R[a] for a point ``own`` metres along branch i."""
            r = np.zeros(nb)
            r[i] = own
            child, a = i, parent[i]
            while a >= 0:
                r[a] = tree.branches[child].attach * tree.branches[a].length
                child, a = a, parent[a]
            return r

        self.mass = np.zeros(nb)
        self.inertia = np.zeros(nb)
        rcom = np.zeros((nb, nb))
        for i, b in enumerate(tree.branches):
            m, moments = cylinder_inertia(b, branch_density(tree, b))
            self.mass[i], self.inertia[i] = m, moments[1]  # about the hinge (y) direction
            rcom[i] = path_coeffs(i, b.length / 2)
        self.A = (rcom * self.mass[:, None]).T @ rcom  # A_ac = sum_b m_b R_b[a] R_b[c]
        self.mr = self.mass @ rcom  # sum_b m_b R_b[a]
        self._path_coeffs, self._idx = path_coeffs, idx
        self._lengths = {b.name: b.length for b in tree.branches}
        g_name = tree.grasp_branch if grasp_branch is None else grasp_branch
        frac = tree.grasp_fraction if grasp_fraction is None else float(grasp_fraction)
        gb = idx[g_name]
        self.rc = path_coeffs(gb, frac * tree.branches[gb].length)

        kp_all, kd_all = np.zeros(self.nv), np.zeros(self.nv)
        inferred = {n: j for j, n in enumerate(tree.inferred)}
        kp, kd = np.atleast_1d(np.asarray(kp, float)), np.atleast_1d(np.asarray(kd, float))
        for dd, i in enumerate(dof_branches):
            n = names[i]
            if n in inferred:
                kp_all[dd], kd_all[dd] = kp[inferred[n]], kd[inferred[n]]
            else:
                kp_all[dd], kd_all[dd] = tree.fixed_gains(n)
        self.kp, self.kd = kp_all, kd_all
        self.q_rest = self._rest()
        self.c_rest = self.grasp_point(self.q_rest)

    # ---- kinematics -------------------------------------------------------------------------
    def phi(self, q):
        return self.phi0 - self.S @ q

    def _dir(self, phi):
        """[nb, 3] e'(phi): derivative of the unit branch vector with respect to phi."""
        return -np.sin(phi)[:, None] * self.h + np.cos(phi)[:, None] * self.z

    def grasp_point(self, q) -> np.ndarray:
        phi = self.phi(q)
        e = np.cos(phi)[:, None] * self.h + np.sin(phi)[:, None] * self.z
        return self.base + self.rc @ e

    def point(self, q, branch: str, fraction: float) -> np.ndarray:
        """World position [3] of the point at ``fraction`` of ``branch`` for angles ``q``."""
        phi = self.phi(q)
        e = np.cos(phi)[:, None] * self.h + np.sin(phi)[:, None] * self.z
        i = self._idx[branch]
        return self.base + self._path_coeffs(i, fraction * self._lengths[branch]) @ e

    def rotation(self, q, q0, branch: str) -> np.ndarray:
        """Rotation vector [3] (rad, world axes) of ``branch`` at ``q`` from its pose at ``q0``:
        a turn by the change of its elevation about the plane's normal ``h x z``."""
        i = self._idx[branch]
        return (self.phi(q)[i] - self.phi(q0)[i]) * np.cross(self.h, self.z)

    # ---- dynamics ---------------------------------------------------------------------------
    def _gravity_q(self, q):
        """S^T Q_gravity [nv]."""
        ep = self._dir(self.phi(q))
        return self.S.T @ (self.mr * (ep @ self.g))

    def _rest(self) -> np.ndarray:
        fun = lambda q: -self._gravity_q(q) - self.kp * q
        sol = root(fun, np.zeros(self.nv), method="hybr", options={"xtol": 1e-13})
        if np.max(np.abs(fun(sol.x))) > 1e-10 * (1.0 + np.max(np.abs(self._gravity_q(sol.x)))):
            raise RuntimeError(f"static equilibrium not found: {sol.message}")
        return sol.x

    def acceleration(self, q, v, force: float) -> np.ndarray:
        """qddot [nv] at angles q, speeds v and a force (N) along ``direction`` at C."""
        phi = self.phi(q)
        phid = -self.S @ v
        diff = phi[:, None] - phi[None, :]
        m_phi = self.A * np.cos(diff) + np.diag(self.inertia)
        hvec = (self.A * np.sin(diff)) @ (phid**2)
        ep = self._dir(phi)
        q_ext = self.mr * (ep @ self.g) + self.rc * (ep @ (force * self.direction))
        tau = -self.kp * q - self.kd * v
        rhs = self.S.T @ (hvec - q_ext) + tau
        return np.linalg.solve(self.S.T @ m_phi @ self.S, rhs)

    def rollout(self, forces, dt: float, interp: str = "linear", rtol: float = 1e-11) -> np.ndarray:
        """tau [T] (m) at ``t_k = k dt`` under force samples ``forces`` [T] (N, along the pull
        direction), starting at rest at t = 0. ``interp``: "linear" (first-order hold) or
        "hold" (sample k from t_k to t_{k+1})."""
        q = self.rollout_q(forces, dt, interp, rtol)
        out = [self.grasp_point(qk) for qk in q]
        return (np.asarray(out) - self.c_rest) @ self.direction

    def rollout_q(self, forces, dt: float, interp: str = "linear", rtol: float = 1e-11):
        """The hinge angles q [T, nv] at ``t_k = k dt`` of :meth:`rollout`."""
        f = np.asarray(forces, float)
        n = f.size
        if interp == "linear":
            # kinks of the interpolated signal: samples where the slope changes
            kinks = [
                k
                for k in range(1, n - 1)
                if abs(f[k + 1] - 2 * f[k] + f[k - 1]) > 1e-12 * (1 + abs(f[k]))
            ]
        elif interp == "hold":
            kinks = [k for k in range(1, n) if f[k] != f[k - 1]]
        else:
            raise ValueError(f"interp: 'linear' or 'hold', got {interp!r}")
        bounds = [0] + kinks + [n - 1]
        y = np.concatenate([self.q_rest, np.zeros(self.nv)])
        nv = self.nv
        out = [self.q_rest]
        for lo, hi in itertools.pairwise(bounds):
            if hi == lo:
                continue

            def rhs(t, y, lo=lo, hi=hi):
                if interp == "linear":  # the sample interval holding t, within this segment
                    k = min(max(math.floor(t / dt), lo), hi - 1)
                    fk = f[k] + (f[k + 1] - f[k]) * (t / dt - k)
                else:
                    fk = f[lo]
                return np.concatenate([y[nv:], self.acceleration(y[:nv], y[nv:], fk)])

            t_eval = np.arange(lo + 1, hi + 1) * dt
            sol = solve_ivp(
                rhs, (lo * dt, hi * dt), y, method="DOP853", t_eval=t_eval, rtol=rtol, atol=1e-13
            )
            if not sol.success:
                raise RuntimeError(sol.message)
            out.extend(sol.y[:nv, j] for j in range(sol.y.shape[1]))
            y = sol.y[:, -1]
        return np.asarray(out)
