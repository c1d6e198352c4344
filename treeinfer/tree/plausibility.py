"""What a tree can do, for the plausibility checks: findings (:class:`Finding`), the thresholds,
the compliance range and reach of the grasp point, and the simulation cost. Re-exported by
:mod:`treeinfer.evaluation.checks`."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from .description import Tree, world_frames

POOR_FIT_EXIT_CODE = 4

# thresholds (ratios are observed / allowed)
SCALE_WARN = 3.0  # compliance this far outside the prior box's range: warning
SCALE_ERROR = 30.0  # ... this far: error (a unit mistake, not a prior box a little too narrow)
MIXED_RATIO = 10.0  # files whose compliance differs from the median by this factor
REST_FRACTION = 0.25  # |x[0]| beyond this share of the displacement's range ...
REST_MIN = 0.01  # ... and beyond 1 cm is not "at rest"
REST_FORCE = 0.1  # "force near zero at the start": below this share of max |force|
VELOCITY_MISMATCH = 0.5  # relative misfit of integrated velocity vs displacement
MAX_BRANCH_SPEED = 2.0  # m/s; the speed check's floor when the tree's inertia is unknown
SPEED_MARGIN = 1.25  # the energy bound on the grasp point's speed, times this, is "too fast"
ZERO_ATOL = 1e-12


class Finding(NamedTuple):
    """One result of a check: ``severity`` ``"error"`` or ``"warning"``; ``file`` the file (or
    tree) it concerns; ``check`` a short id; ``message`` the evidence in words."""

    severity: str
    file: str
    check: str
    message: str

    def __str__(self) -> str:
        return f"{self.severity}: {self.file}: {self.message}"


def errors_of(findings: Sequence[Finding]) -> list[Finding]:
    return [f for f in findings if f.severity == "error"]


def format_findings(findings: Sequence[Finding]) -> str:
    """One line per finding, errors first (for the CLI)."""
    order = sorted(findings, key=lambda f: (f.severity != "error", f.file, f.check))
    return "\n".join(str(f) for f in order)


# ---- what the tree can do --------------------------------------------------------------------
def _lever_terms(tree: Tree, grasp_fraction: float | None = None) -> list[tuple[str, float]]:
    """``[(joint name, s_j)]``: downward motion of the grasp point per radian at each hinge
    between the root and the grasped branch (fixed branches have no hinge)."""
    frames = world_frames(tree)
    g = np.asarray(tree.gravity, float)
    g_hat = g / np.linalg.norm(g)
    frac = tree.grasp_fraction if grasp_fraction is None else float(grasp_fraction)
    gb = tree.branch(tree.grasp_branch)
    pos, rot = frames[gb.name]
    p = pos + rot @ np.array([frac * gb.length, 0.0, 0.0])
    out = []
    for name in tree.ancestors(tree.grasp_branch):
        if tree.branch(name).fixed:
            continue
        o, r = frames[name]
        axis = r[:, 1]  # hinge about the branch frame's y-axis
        out.append((name, float(g_hat @ np.cross(axis, p - o))))
    return out


def lever_arm_compliance(
    tree: Tree, kp: dict[str, float] | None = None, grasp_fraction: float | None = None
) -> float:
    """Small-rotation compliance (m/N) at the *unloaded geometric* pose, ignoring gravity:
    ``sum_j s_j^2 / Kp_j`` (module docstring). ``kp``: stiffness of inferred joints by name
    (N m/rad); other joints use the tree's fixed gains."""
    kp = kp or {}
    total = 0.0
    for name, s in _lever_terms(tree, grasp_fraction):
        k = kp.get(name, tree.fixed_gains(name)[0])
        total += s * s / float(k)
    return total


def static_compliance(
    tree: Tree, kp: dict[str, float] | None = None, grasp_fraction: float | None = None
) -> float:
    """Quasi-static compliance (m/N) of the grasp point along gravity at the tree's settled
    rest pose, gravity's stiffness included: ``s K^-1 s^T`` with ``s = g_hat . J_site`` (the
    site Jacobian) and ``K`` the Jacobian of the static joint torque (springs + gravity), both
    from plain MuJoCo at the pose :func:`treeinfer.simulator.settle_reference` finds. ``inf``
    when the pose is not stable (``K`` not positive definite).

    Why not only the lever-arm formula: a soft joint sags under the branch's own weight, which
    moves the grasp point and changes its lever arms several-fold (tested against MuJoCo).
    """
    m, sid = _compliance_model(tree, grasp_fraction)
    return _model_compliance(tree, m, sid, kp or {})


def _compliance_model(tree: Tree, grasp_fraction: float | None):
    """The tree's MuJoCo model (grasp site moved to ``grasp_fraction``) and the site's id."""
    import mujoco

    from .export import GRASP_SITE, to_mjmodel

    m = to_mjmodel(tree)
    sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, GRASP_SITE)
    if grasp_fraction is not None:
        gb = tree.branch(tree.grasp_branch)
        m.site_pos[sid] = np.array([float(grasp_fraction) * gb.length, 0.0, 0.0])
    return m, sid


def _model_compliance(tree: Tree, m, sid: int, kp: dict[str, float], out=None) -> float:
    """:func:`static_compliance` on a model from :func:`_compliance_model` (its joint
    stiffnesses set to ``kp`` first). ``out`` (a dict): receives ``mobility``, the largest
    eigenvalue of ``J M^-1 J^T`` (1/kg) at the settled pose, ``J`` the grasp site's
    translational Jacobian and ``M`` the joint-space mass matrix: a site velocity v costs at
    least the kinetic energy ``v^2 / (2 mobility)``."""
    import mujoco

    settle_reference = _sim_attr("settle_reference")
    for name, k in kp.items():
        j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)
        m.jnt_stiffness[j] = float(k)
    q0 = settle_reference(m)
    d = mujoco.MjData(m)

    def torque(q):
        d.qpos[:] = q
        d.qvel[:] = 0
        mujoco.mj_forward(m, d)
        return d.qfrc_passive - d.qfrc_bias

    h = 1e-6
    kmat = np.zeros((m.nv, m.nv))
    for i in range(m.nv):
        e = np.zeros(m.nq)
        e[i] = h
        kmat[:, i] = -(torque(q0 + e) - torque(q0 - e)) / (2 * h)
    kmat = 0.5 * (kmat + kmat.T)
    d.qpos[:] = q0
    mujoco.mj_forward(m, d)
    jacp = np.zeros((3, m.nv))
    mujoco.mj_jacSite(m, d, jacp, None, sid)
    if out is not None:
        mass = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, mass)  # the (m, d, dst) signature of every supported MuJoCo (>= 3.10)
        mob = jacp @ np.linalg.solve(mass, jacp.T)
        out["mobility"] = float(np.max(np.linalg.eigvalsh(0.5 * (mob + mob.T))))
    g = np.asarray(tree.gravity, float)
    s = (g / np.linalg.norm(g)) @ jacp
    try:
        np.linalg.cholesky(kmat)
    except np.linalg.LinAlgError:
        return math.inf
    return float(s @ np.linalg.solve(kmat, s))


def _sim_attr(name: str):
    """``name`` from the simulator package (``treeinfer.sim`` after the restructuring, else
    ``treeinfer.simulator``)."""
    import importlib

    for mod in ("treeinfer.sim.reference", "treeinfer.sim", "treeinfer.simulator"):
        try:
            m = importlib.import_module(mod)
        except ImportError:
            continue
        if hasattr(m, name):
            return getattr(m, name)
    raise ImportError(f"treeinfer has no simulator attribute {name!r}")


MAX_SUBSTEPS = 2000  # simulation steps per observation beyond which a run cannot finish


def simulation_cost_check(
    tree: Tree,
    obs_dt: float,
    tree_file: str | os.PathLike | None = None,
    max_substeps: int = MAX_SUBSTEPS,
) -> list[Finding]:
    """An error if the prior box's stiffest corner needs more than ``max_substeps`` simulation
    steps per observation (the simulator's own rule, :func:`choose_substeps`): a tiny twig with
    a huge Kp bound would otherwise run for days. Names the Kp bound to lower."""
    import mujoco

    from .export import to_mjmodel

    choose_substeps = _sim_attr("choose_substeps")
    m = to_mjmodel(tree)
    ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, n) for n in tree.inferred]
    kp_max = [tree.bounds[n].kp[1] for n in tree.inferred]
    n = int(choose_substeps(m, ids, kp_max, float(obs_dt)))
    if n <= max_substeps:
        return []
    name = str(tree_file) if tree_file is not None else f"tree '{tree.name}'"
    return [
        Finding(
            "error",
            name,
            "simulation-cost",
            f"the prior box's upper Kp bounds ({', '.join(f'{k:g}' for k in kp_max)} N m/rad) on "
            f"branches this light need {n} simulation steps per {obs_dt:g} s sample (limit "
            f"{max_substeps}); lower inference.prior.kp's upper bound or check the branch "
            "masses",
        )
    ]


COMPLIANCE_DIAGONAL = 9  # points along the prior box's diagonal in compliance_range
COMPLIANCE_CORNERS_UP_TO = 4  # inferred joints up to which every corner is evaluated too


def compliance_range(tree: Tree, grasp_fraction: float | None = None) -> tuple[float, float]:
    """(least, most) quasi-static compliance in m/N over the prior box's stiffnesses
    (:func:`response_range`'s first two)."""
    return response_range(tree, grasp_fraction)[:2]


def response_range(tree: Tree, grasp_fraction: float | None = None) -> tuple[float, float, float]:
    """(least, most) quasi-static compliance in m/N over the prior box's stiffnesses, and the
    grasp point's largest mobility (1/kg, see :func:`_model_compliance`) over the same poses:
    the smallest and largest :func:`static_compliance` along the box's diagonal in log space (every
    inferred Kp at the same fraction of its log range, :data:`COMPLIANCE_DIAGONAL` points) and,
    up to :data:`COMPLIANCE_CORNERS_UP_TO` inferred joints, at every corner.

    Why not the two ends alone: the compliance is not monotone in the stiffness. A soft joint
    lets the branch sag until it hangs along gravity, where a downward pull has little lever
    arm: on the three-branch example it is 0.016 m/N with every Kp at its lower bound (5), 0.110
    at 23 and 0.009 at 500, so the ends missed the largest by 7x and data simulated from the
    example's own model inside its box drew a false "displacement in cm?" warning."""
    import itertools

    names = list(tree.inferred)
    lo = np.log([tree.bounds[n].kp[0] for n in names])
    hi = np.log([tree.bounds[n].kp[1] for n in names])
    points = [lo + f * (hi - lo) for f in np.linspace(0.0, 1.0, COMPLIANCE_DIAGONAL)]
    if len(names) <= COMPLIANCE_CORNERS_UP_TO:
        points += [np.where(bits, hi, lo) for bits in itertools.product((0, 1), repeat=len(names))]
    m, sid = _compliance_model(tree, grasp_fraction)
    values, mobility = [], 0.0
    for p in points:
        out: dict = {}
        values.append(_model_compliance(tree, m, sid, dict(zip(names, np.exp(p))), out))
        mobility = max(mobility, out.get("mobility", 0.0))
    finite = [c for c in values if math.isfinite(c)]
    if not finite:
        return math.inf, math.inf, mobility
    # an unstable pose somewhere in the box: no bound on how soft the grasp point can be
    return min(finite), (max(finite) if len(finite) == len(values) else math.inf), mobility


def grasp_reach(tree: Tree, grasp_fraction: float | None = None) -> float:
    """Largest distance (m) from a hinge to the grasp point: the grasp point cannot move
    further than twice this."""
    frames = world_frames(tree)
    frac = tree.grasp_fraction if grasp_fraction is None else float(grasp_fraction)
    gb = tree.branch(tree.grasp_branch)
    pos, rot = frames[gb.name]
    p = pos + rot @ np.array([frac * gb.length, 0.0, 0.0])
    return max(float(np.linalg.norm(p - frames[n][0])) for n in tree.ancestors(tree.grasp_branch))
