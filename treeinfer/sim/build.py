"""Building a :class:`~treeinfer.sim.Simulator`: :func:`make_simulator` compiles a tree (or a
user's MJCF/URDF) to MuJoCo, picks the backend and the step (:func:`choose_substeps` for
stability, :mod:`treeinfer.sim.accuracy` for accuracy)."""

from __future__ import annotations

import math

import numpy as np

from ..errors import ConfigError, TreeFileError
from ..tree.description import Tree
from . import pallas as _pallas_hook
from .simulator import (
    BACKENDS,
    DEFAULT_MAX_SIM_DT,
    FORCE_INTERPS,
    PRIOR_STIFFNESS_HEADROOM,
    STABILITY_MARGIN,
    Simulator,
)

ACCURACIES = ("accurate", "coarse")  # make_simulator(accuracy=...): see its docstring


def _stiff_corner_omega(mj_model, joint_ids: np.ndarray, kp_max: np.ndarray) -> float:
    """Largest natural frequency (rad/s) at the rest pose with inferred joints at ``kp_max``."""
    import mujoco

    d = mujoco.MjData(mj_model)
    mujoco.mj_forward(mj_model, d)
    nv = mj_model.nv
    mass = np.zeros((nv, nv))
    mujoco.mj_fullM(mj_model, d, mass)
    k = np.zeros(nv)
    for j in range(mj_model.njnt):
        k[mj_model.jnt_dofadr[j]] = mj_model.jnt_stiffness[j]
    for jid, kp in zip(joint_ids, kp_max):
        k[mj_model.jnt_dofadr[jid]] = kp
    # generalized eigenvalues of K v = w^2 M v
    lm = np.linalg.cholesky(mass)
    li = np.linalg.inv(lm)
    w2 = np.linalg.eigvalsh(li @ np.diag(k) @ li.T)
    return float(np.sqrt(max(w2.max(), 0.0)))


def choose_substeps(
    mj_model, joint_ids, kp_max, obs_dt: float, max_sim_dt: float = DEFAULT_MAX_SIM_DT
) -> int:
    """Simulation steps per observation so that ``omega_max * dt <= STABILITY_MARGIN``."""
    omega = _stiff_corner_omega(
        mj_model, np.asarray(joint_ids), np.asarray(kp_max) * PRIOR_STIFFNESS_HEADROOM
    )
    dt_max = min(max_sim_dt, STABILITY_MARGIN / omega if omega > 0 else max_sim_dt)
    return max(1, int(math.ceil(obs_dt / dt_max - 1e-9)))


def make_simulator(
    tree: Tree,
    obs_dt: float = 0.01,
    substeps: int | None = None,
    max_sim_dt: float = DEFAULT_MAX_SIM_DT,
    model_file=None,
    settle_iterations: int = 30,
    backend: str = "auto",
    force_interp: str = "linear",
    forces=None,
    sim_tolerance: float | None = None,
    grasp_fraction=None,
    direction=None,
    grasp_branch=None,
    accuracy: str = "accurate",
) -> Simulator:
    """Compile ``tree`` for batched rollouts observed every ``obs_dt`` seconds.

    Args:
      tree: the tree description (geometry, grasp, inferred joints, prior box).
      obs_dt: s, the trajectory sample interval (the CSV files' time step).
      substeps: simulation steps per observation; default: chosen by ``accuracy`` (below).
        ``sim.step_info`` says how it was chosen.
      accuracy: ``"accurate"`` (the default, the step ``treeinfer infer`` takes): the fewest
        substeps that keep the stiffest corner of the prior box stable and ``dt <= max_sim_dt``
        (s), refined until the step-doubling estimate of the discretisation error of ``tau`` is
        at most ``sim_tolerance`` on parameter sets spanning the prior box
        (:func:`treeinfer.sim.accuracy.choose_substeps_for_accuracy`), on ``forces`` when given
        (the data's), else on a representative set of pulls
        (:func:`treeinfer.sim.accuracy.representative_forces`: the standard seeded 3 s pulls,
        peaks 2-8 N, scaled up for a stiff or large tree). The choice is kept on disk with the
        compiled programs, so a later process with the same tree and pulls skips it.
        ``"coarse"``: the stability step only (what ``make_simulator`` took before issue 27:
        0.2-0.5 mm off an independent integration on the benchmark chains, several times faster
        to roll out), for speed studies.
      forces: [B, T] N, the force profiles the simulator will run (the data's), for the
        accuracy-controlled step; ``grasp_fraction``, ``direction`` and ``grasp_branch`` are
        those profiles' (as in :func:`simulate`).
      sim_tolerance: m, the accuracy target (default ``DEFAULT_SIM_TOLERANCE`` = 0.1 mm; the run
        layer passes a tenth of the noise level when it knows it).
      force_interp: ``"linear"`` (first-order hold between force samples, the default) or
        ``"hold"`` (zero-order hold, each sample held until the next); see :func:`simulate`.
      model_file: a user's own MJCF (``.xml``) or URDF file to simulate instead of exporting
        ``tree`` (default: the tree's ``model:`` section, if any); prepared by
        :func:`treeinfer.tree.usermodel.prepare_user_model` (name map, fixed gains, grasp axis,
        inertia and limit checks) with the settings of the tree's ``model:`` section.
      backend: ``"fused"``, ``"mjx"`` or ``"auto"`` (fused when the model is a contact-free
        hinge tree it reproduces, which every tree treeinfer builds is; MJX otherwise). Both
        step the same MuJoCo model and agree with MuJoCo C to float32 rounding; the fused step
        is several times faster and compiles in seconds (``BENCHMARKS.md``).
        ``"pallas"``: the fused step as one GPU kernel per block of rollouts
        (:mod:`treeinfer.sim.pallas`); ``"auto"`` picks it on a GPU.
    """
    import mujoco

    from ..tree.export import GRASP_SITE, to_mjmodel

    if not (isinstance(obs_dt, (int, float)) and math.isfinite(obs_dt) and obs_dt > 0):
        raise ConfigError(f"obs_dt: must be a positive number of seconds, got {obs_dt!r}")
    if substeps is not None and (not isinstance(substeps, int) or substeps < 1):
        raise ConfigError(f"substeps: must be a positive integer, got {substeps!r}")
    if backend not in BACKENDS:
        raise ConfigError(f"backend: must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if force_interp not in FORCE_INTERPS:
        raise ConfigError(
            f"force_interp: must be one of {', '.join(FORCE_INTERPS)}, got {force_interp!r}"
        )
    if not (isinstance(max_sim_dt, (int, float)) and math.isfinite(max_sim_dt) and max_sim_dt > 0):
        raise ConfigError(f"max_sim_dt: must be a positive number of seconds, got {max_sim_dt!r}")
    if accuracy not in ACCURACIES:
        raise ConfigError(f"accuracy: must be one of {', '.join(ACCURACIES)}, got {accuracy!r}")
    if accuracy == "coarse" and (forces is not None or sim_tolerance is not None):
        raise ConfigError(
            "accuracy='coarse' takes the stability step only; forces and sim_tolerance choose "
            "the accuracy-controlled step (accuracy='accurate')"
        )
    if sim_tolerance is not None and not (
        isinstance(sim_tolerance, (int, float))
        and math.isfinite(sim_tolerance)
        and sim_tolerance > 0
    ):
        raise ConfigError(
            f"sim_tolerance: must be a positive number of metres, got {sim_tolerance!r}"
        )
    user = None
    if model_file is not None or tree.model is not None:
        from ..tree.usermodel import prepare_user_model

        user = prepare_user_model(tree, model_file)
    mj_model = to_mjmodel(tree) if user is None else user.mj_model
    bad = [
        mj_model.joint(j).name
        for j in range(mj_model.njnt)
        if mj_model.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE
    ]
    if bad:
        raise TreeFileError(
            f"model: only hinge joints are supported, found other joint types: {bad}"
        )

    def jid(name):
        i = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if i < 0:
            raise TreeFileError(
                f"model: no joint named '{name}' (inferred joints must exist in the model)"
            )
        return i

    joint_ids = np.array([jid(n) for n in tree.inferred], dtype=np.int32)
    dof_ids = np.array([mj_model.jnt_dofadr[j] for j in joint_ids], dtype=np.int32)
    body = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_BODY, tree.grasp_branch)
    if body < 0:
        raise TreeFileError(f"model: no body named '{tree.grasp_branch}' (the grasp branch)")
    site = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_SITE, GRASP_SITE)
    if site < 0 or mj_model.site_bodyid[site] != body:
        raise TreeFileError(f"model: no site '{GRASP_SITE}' on body '{tree.grasp_branch}'")
    axes = {} if user is None else user.axes
    length = tree.branch(tree.grasp_branch).length
    start, end = axes.get(tree.grasp_branch, (np.zeros(3), np.array([length, 0.0, 0.0])))

    prior_lo, prior_hi = tree.bounds_array()
    kp_max = prior_hi[: tree.n_inferred]
    step_info = {"method": "given"}
    if substeps is None:
        substeps = choose_substeps(mj_model, joint_ids, kp_max, obs_dt, max_sim_dt)
        step_info = {
            "method": "stability",
            "stability_substeps": int(substeps),
            "max_sim_dt": float(max_sim_dt),
        }
    mj_model.opt.timestep = obs_dt / substeps
    g = np.asarray(mj_model.opt.gravity, float)
    gdir = g / np.linalg.norm(g)
    hinge_tree = None
    if backend in ("auto", "fused", "pallas"):
        from .fused import UnsupportedModel, from_mjmodel

        try:
            hinge_tree = from_mjmodel(mj_model)
        except UnsupportedModel as e:
            if backend in ("fused", "pallas"):
                raise TreeFileError(f"model: {e}; use backend='mjx'") from None
    branches, branch_axes = {}, {}
    for b in tree.branches:
        i = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_BODY, b.name)
        if i >= 0:
            a, e = axes.get(b.name, (np.zeros(3), np.array([b.length, 0.0, 0.0])))
            branches[b.name] = (int(i), float(np.linalg.norm(e - a)))
            if b.name in axes:
                branch_axes[int(i)] = (np.asarray(a, float), np.asarray(e, float))
    sim = Simulator(
        mj_model=mj_model,
        joint_names=tuple(tree.inferred),
        joint_ids=joint_ids,
        dof_ids=dof_ids,
        grasp_body=int(body),
        grasp_site=int(site),
        grasp_start=start,
        grasp_end=end,
        obs_dt=float(obs_dt),
        substeps=int(substeps),
        gravity_dir=gdir,
        settle_iterations=settle_iterations,
        max_displacement=max(5.0, 2.0 * tree.total_length()),
        backend="mjx" if hinge_tree is None else _pallas_hook.resolve(backend),
        hinge_tree=hinge_tree,
        force_interp=force_interp,
        grasp_fraction=float(tree.grasp_fraction),
        prior_box=(prior_lo, prior_hi),
        branches=branches,
        step_info=step_info,
        branch_axes=branch_axes,
        model_report={} if user is None else user.report,
    )
    if step_info["method"] == "stability" and accuracy == "accurate":
        from .accuracy import with_accurate_step

        sim = with_accurate_step(
            sim,
            forces,
            sim_tolerance,
            max_sim_dt,
            grasp_fraction=grasp_fraction,
            direction=direction,
            grasp_branch=grasp_branch,
        )
    return sim
