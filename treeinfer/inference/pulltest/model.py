"""The static tree-pulling model with angle observations: the stem as a chain of links with
torsional springs, a cable force at a height and angle, the tilt read at inclinometer heights.

The tree (a :class:`~treeinfer.tree.Tree`, so the same description the dynamic model uses):

* link ``root`` from the ground to the root inclinometer's height, hinged at the ground: its
  spring is the root-soil rotation plus the stem's bending below the root clino;
* link ``stem`` from there to the top, hinged at the root clino's height: its spring lumps the
  trunk's bending between the clinos (the pseudo-rigid-body view of a continuous stem);
* upright (``base.pitch_deg: 90``), bending in the world x-z plane with x toward the anchor;
  radius DBH/2 for ``root`` and 0.7 DBH/2 for ``stem`` (a taper guess), wood density 900 kg/m^3
  (700-1000 for these genera): the masses enter only through gravity's small P-Delta term.

The cable pulls at ``sling_height`` along ``(cos a, 0, -sin a)`` (a below horizontal, toward
the anchor). The equilibrium under each recorded force is treeinfer's static solver
(:func:`treeinfer.inference.static.static_equilibria`: clipped Newton on spring + gravity +
the cable's generalised force, exact implicit derivatives). An inclinometer at height z reads
the tilt of the link that holds z (a clino exactly at a hinge reads the link below it), in
the pull plane: ``atan2(u_x, u_z)`` of the link's axis ``u``, from its rest value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import ConfigError
from ...sim import Simulator, make_simulator
from ...sim import fused as hd
from ...tree.description import Bounds, Branch, Tree, make_tree
from ..static.equilibrium import static_equilibria

__all__ = [
    "DENSITY",
    "KP_PRIOR",
    "PullModel",
    "chain_tree",
    "pull_model",
    "model_response",
    "model_tilts",
]

DENSITY = 900.0  # kg/m^3, wood of Rhizophora/Avicennia (700-1000; Chave et al. 2009 via the paper)
KP_PRIOR = (1.0e3, 1.0e8)  # N m/rad: the log-uniform prior box of each joint (trees, not twigs)
STEM_TAPER = 0.7  # stem radius / root radius
# Newton steps per force sample: tilts of a few degrees are within float32 rounding after 3-4
# steps from the rest (the solver's default 30 is for large deflections of light branches);
# a sample that has not converged is flagged unstable (tests check against the closed form)
NEWTON_ITERATIONS = 8


@dataclass(frozen=True)
class PullModel:
    """A compiled static pulling model: ``joints`` the inferred hinges (columns of ``kp``),
    ``sensors`` channel -> link whose tilt it reads, ``load`` the link and the fraction of its
    length where the cable pulls, ``direction`` the cable's unit world vector."""

    tree: Tree
    sim: Simulator
    joints: tuple[str, ...]
    sensors: dict[str, str]
    load_branch: str
    load_fraction: float
    direction: tuple[float, float, float]
    cable_angle: float
    sling_height: float


def chain_tree(
    sling_height: float,
    clino_heights: dict[str, float],
    height: float,
    dbh: float,
    density: float = DENSITY,
    kp_prior: tuple[float, float] = KP_PRIOR,
) -> tuple[Tree, dict[str, str], str, float]:
    """The two-link chain of the module docstring: ``(tree, sensors, load_branch,
    load_fraction)``. ``clino_heights`` must hold ``root`` (the stem hinge's height)."""
    if "root" not in clino_heights:
        raise ConfigError("chain_tree: the root inclinometer's height is needed (the hinge)")
    h_r = float(clino_heights["root"])
    top = max(
        float(height) if math.isfinite(height) else 0.0, sling_height, *clino_heights.values()
    )
    top = max(top, h_r + 0.1)
    if not (h_r > 0 and sling_height > 0):
        raise ConfigError(f"heights must be > 0 m: root clino {h_r}, sling {sling_height}")
    r = float(dbh) / 2 if math.isfinite(dbh) and dbh > 0 else 0.1
    branches = [
        Branch("root", None, h_r, r),
        Branch("stem", "root", top - h_r, r * STEM_TAPER),
    ]
    if sling_height <= h_r:
        load, frac = "root", sling_height / h_r
    else:
        load, frac = "stem", (sling_height - h_r) / (top - h_r)
    tree = make_tree(
        branches,
        grasp_branch=load,
        grasp_fraction=frac,
        inferred=("root", "stem"),
        bounds=Bounds(kp=kp_prior),
        name="pull_test_chain",
        base_pitch_deg=90.0,
        density=density,
        parameters=("kp",),
    )
    sensors = {c: ("root" if z <= h_r + 1e-9 else "stem") for c, z in clino_heights.items()}
    return tree, sensors, load, frac


def pull_model(setup, density: float = DENSITY, kp_prior=KP_PRIOR) -> PullModel:
    """The model of one test from its set-up (:class:`treeinfer.data.PullSetup`)."""
    heights = {c: z for c, (_, z) in setup.channel_heights.items()}
    tree, sensors, load, frac = chain_tree(
        setup.sling_height, heights, setup.height, setup.dbh, density, kp_prior
    )
    # the static solver never steps in time: the coarse (stability-only) step choice is enough
    sim = make_simulator(tree, obs_dt=0.1, backend="fused", accuracy="coarse")
    a = setup.cable_angle
    return PullModel(
        tree=tree,
        sim=sim,
        joints=tree.inferred,
        sensors=sensors,
        load_branch=load,
        load_fraction=frac,
        direction=(math.cos(a), 0.0, -math.sin(a)),
        cable_angle=a,
        sling_height=float(setup.sling_height),
    )


def _body_ids(model: PullModel) -> list[int]:
    import mujoco

    m = model.sim.mj_model
    return [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, b) for b in model.sensors.values()]


def model_tilts(
    model: PullModel, kp, forces, iterations: int = NEWTON_ITERATIONS
) -> tuple[jax.Array, jax.Array]:
    """Tilt change of each sensor's link under each force: ``[P, C, T]`` rad (channels in the
    order of ``model.sensors``) and ``stable`` [P]. ``kp`` [P, R] N m/rad in the order of
    ``model.joints``; ``forces`` [T] N along the cable. Differentiable in ``kp``."""
    tilts, _, _, stable = model_response(model, kp, forces, iterations)
    return tilts, stable


def model_response(
    model: PullModel, kp, forces, iterations: int = NEWTON_ITERATIONS
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """:func:`model_tilts` and what the creep element needs: ``(tilts [P, C, T], dq [P, R, T]``
    each inferred joint's deflection from its rest, ``jac [P, C, R]`` the tilts' derivative in
    the joint angles at the rest, ``stable [P])``. The spring's moment change is ``kp * dq``."""
    if tuple(model.sim.dof_ids.shape) != (len(model.joints),):
        raise ConfigError("model_tilts: the simulator's inferred joints are not the model's")
    eq = static_equilibria(
        model.sim,
        kp,
        jnp.atleast_2d(forces),
        grasp_fraction=model.load_fraction,
        direction=np.asarray(model.direction),
        grasp_branch=model.load_branch,
        tree=model.tree,
        iterations=iterations,
    )
    t = model.sim.hinge_tree
    bodies = _body_ids(model)
    dofs = np.asarray(model.sim.dof_ids)

    def tilt(q):  # [nv] -> [C]: each sensor link's angle in the x-z plane
        kin = hd.kinematics(t, [q[i] for i in range(t.nv)])
        out = []
        for b in bodies:
            rot = kin.rot[b]  # the link's axis is its local x: the first column
            out.append(jnp.arctan2(jnp.asarray(rot[0][0]), jnp.asarray(rot[2][0])))
        return jnp.stack(out)

    rest = jax.vmap(tilt)(eq.q_rest)  # [P, C]
    loaded = jax.vmap(jax.vmap(tilt))(eq.q[:, 0])  # [P, T, C]
    tilts = jnp.swapaxes(loaded - rest[:, None, :], 1, 2)
    dq = jnp.swapaxes((eq.q[:, 0] - eq.q_rest[:, None, :])[..., dofs], 1, 2)  # [P, R, T]
    jac = jax.vmap(jax.jacfwd(tilt))(eq.q_rest)[..., dofs]  # [P, C, R]
    return tilts, dq, jac, eq.stable[:, 0]
