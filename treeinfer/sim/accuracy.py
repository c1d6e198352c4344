"""Accuracy-controlled simulation step: refine the substeps until the discretisation error of
the displacement is below a tolerance tied to the data.

The simulator's step (MuJoCo's ``implicitfast``: semi-implicit Euler with implicit damping) is
first-order accurate, so a step that is merely *stable* can be off by a millimetre or more on a
soft, swinging branch (``tests/test_accuracy.py`` measures it against an independent
Lagrangian reference). The error depends on the gains and on the force profiles, so it is
estimated where it matters:

* **Parameter sets** spanning the prior box: its corners in log space and its centre (all
  ``2^(2R)`` corners up to R = 2 inferred joints; beyond that the four corners where every
  joint takes the same end of its Kp and Kd ranges plus random corners, ``max_params`` in all),
  and a few seeded log-uniform interior points.
* **Force profiles**: the actual ones (the data's), with their grasp points and directions.
* **Step doubling**: ``err(s) = 2 max |tau_s - tau_2s|`` over time, profiles and parameter sets,
  where ``tau_s`` is the rollout with ``s`` substeps per observation. For a first-order method
  ``tau_s - tau_2s`` is half the error of ``tau_s``, so the factor 2 makes the estimate
  conservative (for parts of the error that converge faster it overestimates).

Starting from the stability choice, ``s`` grows (by the first-order prediction
``s * err / tol``, at least by one) until ``err(s) <= tol``. Every candidate runs through one
compiled program: the substep count is a traced loop bound there, and the forces are padded to
their shape bucket (:mod:`treeinfer.sim.startup`), so a new data set of a bucket reuses the program
compiled for an earlier one (from the persistent compilation cache in a new process).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings

import jax
import numpy as np

from ..errors import ConfigError
from . import DEFAULT_MAX_SIM_DT, DEFAULT_SIM_TOLERANCE, Simulator, _simulate, make_simulator
from .startup import device_array

MAX_SUBSTEPS = 400  # per observation: the refinement stops here (and warns)
NOISE_FRACTION = 0.1  # default tolerance: this fraction of the noise level when it is known


def default_tolerance(noise_sd: float | None = None) -> float:
    """m: a tenth of the displacement noise's standard deviation ``noise_sd`` (m) when it is
    known, else ``DEFAULT_SIM_TOLERANCE`` (0.1 mm)."""
    if noise_sd is None:
        return DEFAULT_SIM_TOLERANCE
    if not (math.isfinite(noise_sd) and noise_sd > 0):
        raise ConfigError(f"noise level: must be a positive number of metres, got {noise_sd!r}")
    return NOISE_FRACTION * float(noise_sd)


def prior_box_params(
    prior_lo, prior_hi, max_params: int = 17, n_interior: int = 8, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """(kp [N, R], kd [N, R]): corners of the prior box in log space, its log-centre and
    ``n_interior`` seeded log-uniform interior points (the error is not monotone in the gains:
    a soft interior point can exceed every corner).

    ``prior_lo``, ``prior_hi``: [2R] the box (Kp of the R joints, then Kd), natural units;
    ``max_params`` caps the corners plus the centre."""
    lo, hi = np.log(np.asarray(prior_lo, float)), np.log(np.asarray(prior_hi, float))
    dim = lo.size
    if 2**dim + 1 <= max_params:
        bits = (np.arange(2**dim)[:, None] >> np.arange(dim)[None, :]) & 1
    else:
        r = dim // 2
        same = np.array([[a] * r + [b] * r for a in (0, 1) for b in (0, 1)])
        rng = np.random.default_rng(seed)
        extra = rng.integers(0, 2, size=(max(max_params - 5, 0), dim))
        bits = np.concatenate([same, extra])
    inner = np.random.default_rng(seed + 1).uniform(lo, hi, size=(n_interior, dim))
    corners = np.unique(np.where(bits == 1, hi, lo), axis=0)
    pts = np.concatenate([corners, ((lo + hi) / 2)[None], inner])
    x = np.exp(pts)
    r = dim // 2
    return x[:, :r], x[:, r:]


REPRESENTATIVE_PULLS = 8  # mixed ramp-hold-release / hold pulls of the representative set
REPRESENTATIVE_DURATION = 3.0  # s: the length of a typical recorded pull (README, examples)
TYPICAL_SAG_FRACTION = 0.1  # of the grasp point's reach: the sag a typical pull's peak gives
MAX_PEAK_SCALE = 1e3  # a bound on the scaling (a model far outside tree scales)


def typical_peak_scale(sim: Simulator) -> float:
    """How much the standard pulls' peaks (2-8 N, :data:`treeinfer.data.forces.DEFAULT_PEAK_RANGE`)
    are scaled up so that they bend THIS tree as a typical pull does, >= 1.

    The static compliance of the grasp point along the pull (gravity) at the geometric rest
    pose, ``c = j^T K^-1 j`` (``j``: the grasp site's Jacobian along gravity per dof, ``K``: the
    joints' stiffness, inferred joints at the prior box's log-centre Kp), gives the sag of the
    largest standard peak, ``8 N * c``. When that is below ``TYPICAL_SAG_FRACTION`` of the
    grasp point's distance from the base (a stiff or large tree, which a robot pulls harder),
    the peaks are scaled up to reach it; otherwise the standard pulls are kept (the example
    trees: sags of a few cm to tens of cm). The discretisation error grows with the motion, so
    scaling up and never down keeps the check conservative. A linear, gravity-free estimate:
    it sets a force scale, not a prediction."""
    import mujoco

    from ..data.forces import DEFAULT_PEAK_RANGE

    m = sim.mj_model
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    jac = np.zeros((3, m.nv))
    mujoco.mj_jacSite(m, d, jac, None, sim.grasp_site)
    j = np.asarray(sim.gravity_dir, float) @ jac
    k = np.zeros(m.nv)
    for jid in range(m.njnt):
        k[m.jnt_dofadr[jid]] = m.jnt_stiffness[jid]
    lo, hi = (np.asarray(b, float)[: sim.n_joints] for b in sim.prior_box)
    k[np.asarray(sim.dof_ids)] = np.sqrt(lo * hi)
    ok = k > 0  # a dof without a spring: no static sag to speak of; left out
    compliance = float(np.sum(j[ok] ** 2 / k[ok]))
    base = d.xpos[m.body_rootid[sim.grasp_body]]  # the tree's root body: its base
    reach = float(np.linalg.norm(d.site_xpos[sim.grasp_site] - base))
    sag = DEFAULT_PEAK_RANGE[1] * compliance
    if not (sag > 0 and reach > 0):
        return 1.0
    return float(min(MAX_PEAK_SCALE, max(1.0, TYPICAL_SAG_FRACTION * reach / sag)))


def representative_forces(
    sim_or_obs_dt, duration: float = REPRESENTATIVE_DURATION, n: int = REPRESENTATIVE_PULLS
) -> np.ndarray:
    """[n, T] N: the pulls the accuracy check runs when no data are given (the API's
    :func:`~treeinfer.sim.make_simulator` without ``forces``): the project's standard seeded set
    (:func:`treeinfer.data.forces.profile_set` ``"mixed"``, seed 0: ramp-hold-release and hold pulls
    of ``duration`` s with peaks 2-8 N, the set ``treeinfer simulate``, ``demo`` and
    ``calibrate`` draw from), sampled every ``obs_dt``. Given a :class:`Simulator`, the peaks
    are scaled by :func:`typical_peak_scale` (a stiff or large tree is pulled harder)."""
    from ..data.forces import profile_set

    if isinstance(sim_or_obs_dt, Simulator):
        dt, scale = sim_or_obs_dt.obs_dt, typical_peak_scale(sim_or_obs_dt)
    else:
        dt, scale = float(sim_or_obs_dt), 1.0
    return scale * profile_set("mixed", n=n, duration=duration, dt=dt, seed=0)


@functools.partial(jax.jit, static_argnums=(0, 6))
def _rollout_tau(sim, kp, kd, forces, frac, dirs, grasp_branch, substeps):
    """``(tau, stable)`` of the check's rollouts with ``substeps`` (a traced int32) per
    observation; ``frac``, ``dirs`` may be None (the simulator's own grasp point, the pull
    along gravity).

    The rollout is a stored ``jax.export`` program keyed without the step
    (:func:`treeinfer.sim.startup.stored_export`, :meth:`~treeinfer.sim.Simulator.program_key`):
    a new process on a new recording, whose step this check is about to choose, inlines it
    instead of tracing the simulator (the Pallas kernel and the settle: 0.5-0.7 s of a GPU cold
    start, BENCHMARKS.md) and loads its XLA program from the persistent cache; this jit keeps it
    in memory for the process."""
    from .startup import stored_export

    has = (frac is not None, dirs is not None)
    args = [a for a in (kp, kd, forces, frac, dirs, substeps) if a is not None]

    def run(kp, kd, forces, *rest):
        rest = list(rest)
        frac = rest.pop(0) if has[0] else None
        dirs = rest.pop(0) if has[1] else None
        out = _simulate(
            sim, kp, kd, forces, frac, direction=dirs, grasp_branch=grasp_branch,
            substeps=rest[0],
        )  # fmt: skip
        return out.tau, out.stable

    shapes = tuple((tuple(a.shape), str(a.dtype)) for a in args)
    key = ("accuracy.step_check", sim.program_key(True), grasp_branch, has, shapes)
    exported = stored_export(run, args, repr(key))
    return run(*args) if exported is None else exported.call(*args)


def _bucketed(forces: np.ndarray, frac, dirs, gb):
    """The check's inputs padded to the shape bucket of ``forces [B, T]``
    (:mod:`treeinfer.sim.startup`), so the step-doubling program is compiled once per bucket, not
    once per data set: steps hold each row's last force (the simulator holds it after the last
    sample anyway), padded rows repeat the last row (its grasp point, direction and branch too).
    A padded row or step is simulated and then cut off, never part of the error estimate."""
    from .startup import steps_bucket, trajectories_bucket

    b, t = forces.shape
    nb, nt = trajectories_bucket(b), steps_bucket(t)
    rows = np.minimum(np.arange(nb), b - 1)
    out = forces[rows][:, np.minimum(np.arange(nt), t - 1)]

    def per_row(x, ndim: int):  # a per-profile argument ([B] or [B, 3]) follows the rows
        return x if x is None or x.ndim < ndim else x[rows]

    if isinstance(gb, tuple):
        gb = tuple(gb[i] for i in rows)
    return out, per_row(frac, 1), per_row(dirs, 2), gb


def choose_substeps_for_accuracy(
    sim_or_tree,
    forces,
    tol: float | None = None,
    max_sim_dt: float = DEFAULT_MAX_SIM_DT,
    *,
    obs_dt: float | None = None,
    noise_sd: float | None = None,
    grasp_fraction=None,
    direction=None,
    grasp_branch=None,
    max_params: int = 17,
    max_substeps: int = MAX_SUBSTEPS,
    **make_kwargs,
) -> tuple[int, float]:
    """Substeps per observation whose estimated displacement error is at most ``tol``.

    Args:
      sim_or_tree: a :class:`~treeinfer.sim.Simulator` (its ``obs_dt``, backend, force
        interpolation and prior box are used) or a :class:`~treeinfer.tree.description.Tree` (then
        ``obs_dt`` is required and ``make_kwargs`` go to :func:`make_simulator`).
      forces: [B, T] N, the force profiles to be simulated (the data's).
      tol: m, the accuracy target on ``tau``; default :func:`default_tolerance` of ``noise_sd``.
      max_sim_dt: s, upper bound on the simulation step (as in :func:`make_simulator`).
      grasp_fraction, direction, grasp_branch: the profiles' grasp points and pull directions,
        as in :func:`treeinfer.sim.simulate`.
      max_params: how many parameter sets of the prior box to check (see the module docstring).
      max_substeps: stop refining here; the result then exceeds ``tol`` and a warning says so.

    Returns:
      (substeps, estimated_error): the chosen substeps (at least the stability choice) and the
      step-doubling estimate of the largest error of ``tau`` with them, in metres.
    """
    if isinstance(sim_or_tree, Simulator):
        sim = sim_or_tree
    else:
        if obs_dt is None:
            raise ConfigError("choose_substeps_for_accuracy: obs_dt is required with a tree")
        sim = make_simulator(sim_or_tree, obs_dt=obs_dt, max_sim_dt=max_sim_dt, **make_kwargs)
    tol = default_tolerance(noise_sd) if tol is None else float(tol)
    if not (math.isfinite(tol) and tol > 0):
        raise ConfigError(f"sim_tolerance: must be a positive number of metres, got {tol!r}")
    forces = np.atleast_2d(np.asarray(forces, float))
    if forces.ndim != 2 or forces.shape[1] < 1 or not np.all(np.isfinite(forces)):
        raise ConfigError(f"forces: expected a finite [B, T] array, got shape {forces.shape}")
    kp, kd = prior_box_params(*sim.prior_box, max_params=max_params)
    dtype = sim.dtype
    frac = None if grasp_fraction is None else np.asarray(grasp_fraction, dtype)
    dirs = None if direction is None else np.asarray(direction, dtype)
    gb = (
        grasp_branch
        if grasp_branch is None or isinstance(grasp_branch, str)
        else tuple(grasp_branch)
    )
    n_rows, n_steps = forces.shape
    padded, frac, dirs, gb = _bucketed(forces, frac, dirs, gb)
    # on the device by host-side conversion (startup.device_array): no conversion programs
    args = tuple(
        None if a is None else device_array(a, dtype) for a in (kp, kd, padded, frac, dirs)
    )
    cache: dict[int, np.ndarray] = {}

    def tau(s: int) -> np.ndarray:
        if s not in cache:
            t, ok = _rollout_tau(sim, *args, gb, np.int32(s))
            # the data's rows and steps: a rollout is causal and the padded force holds the
            # last sample, as the simulator does after it, so these are the unpadded values
            t, ok = np.asarray(t)[:, :n_rows, :n_steps], np.asarray(ok)[:, :n_rows]
            # a parameter set that blows up at one step count but not the other would dominate
            # the estimate; the box is checked for stability separately (choose_substeps)
            cache[s] = np.where(ok[..., None], t, np.nan)
        return cache[s]

    def error(s: int) -> float:
        d = np.abs(tau(s) - tau(2 * s))
        return float(2.0 * np.nanmax(d)) if np.any(np.isfinite(d)) else math.inf

    # from the stability choice (not ``sim.substeps``: a simulator built with the default
    # accuracy-controlled step would otherwise never go below the step chosen for 0.1 mm)
    stable_s = int(sim.step_info.get("stability_substeps", sim.substeps))
    s = max(stable_s, math.ceil(sim.obs_dt / max_sim_dt - 1e-9))
    err = error(s)
    if not math.isfinite(err):  # nothing simulates stably: refining cannot help; report it
        warnings.warn(
            "simulation step: no parameter set of the prior box simulates stably on these "
            "forces; the accuracy of the step is unknown",
            stacklevel=2,
        )
        return s, err
    best = (err, s)
    stalled = False
    while err > tol and s < max_substeps:
        s_new = min(max_substeps, max(s + 1, math.ceil(s * err / tol)))
        err_new = error(s_new)
        best = min(best, (err_new, s_new))
        # The error of a convergent step falls in proportion (first order) or faster; when it
        # does not fall at all, rounding (float32) has taken over and smaller steps cannot help.
        stalled = err_new > err * (1.0 - 0.5 * (1.0 - s / s_new))
        s, err = s_new, err_new
        if stalled:
            break
    if err > tol:
        err, s = best
        why = (
            "the estimate stopped falling (rounding: enable float64 with jax_enable_x64)"
            if stalled
            else f"the refinement stops at {max_substeps} substeps per observation"
        )
        warnings.warn(
            f"simulation step: could not reach the tolerance {tol:.3g} m: {why}; using {s} "
            f"substeps ({sim.obs_dt / s:.3g} s) with an estimated error of {err:.3g} m",
            stacklevel=2,
        )
    return s, err


def with_accurate_step(
    sim: Simulator,
    forces=None,
    tol: float | None = None,
    max_sim_dt: float = DEFAULT_MAX_SIM_DT,
    **kwargs,
) -> Simulator:
    """``sim`` with the substeps of :func:`choose_substeps_for_accuracy` (on ``forces``, or on
    :func:`representative_forces` when None) and ``step_info`` recording the tolerance, the
    estimated error and the stability choice."""
    used = representative_forces(sim) if forces is None else forces
    tol = DEFAULT_SIM_TOLERANCE if tol is None else float(tol)
    path = _step_cache_path(sim, used, tol, max_sim_dt, kwargs)
    cached = _read_step_cache(path)
    if cached is None:
        substeps, err = choose_substeps_for_accuracy(sim, used, tol, max_sim_dt, **kwargs)
        _write_step_cache(path, substeps, err)
    else:
        substeps, err = cached
    sim.mj_model.opt.timestep = sim.obs_dt / substeps
    info = {
        "method": "accuracy",
        "stability_substeps": int(sim.step_info.get("stability_substeps", sim.substeps)),
        "max_sim_dt": float(max_sim_dt),
        "tolerance": tol,
        "estimated_error": err,
        "forces": "given" if forces is not None else "representative",
    }
    if forces is None:  # which pulls stood in for the data (module docstring)
        info["representative_peak_n"] = float(np.max(np.abs(used)))
    return dataclasses.replace(sim, substeps=int(substeps), step_info=info)


# ---- the step choice kept on disk ---------------------------------------------------------------
# The step-doubling probes cost 1-3 s of compilation and rollouts per process (BENCHMARKS.md,
# cold start). Their result depends only on the simulator (its content hash), the forces and the
# options, so it is kept next to the compiled-program cache (``TREEINFER_JAX_CACHE``; ``off``
# disables both) and a later process with the same tree and data skips the probes.


def _step_cache_path(sim, forces, tol, max_sim_dt, kwargs):
    """``<cache>/steps/<sha256>.json`` for this choice, or None when the cache is off."""
    import hashlib
    import json
    import os

    from .. import _CACHE_OFF, _cache_tag

    env = os.environ.get("TREEINFER_JAX_CACHE")
    if env is not None and env.strip().lower() in _CACHE_OFF:
        return None
    root = env or os.path.join(os.path.expanduser("~"), ".cache", "treeinfer", "jax")
    h = hashlib.sha256(sim.fingerprint.encode())
    h.update(np.ascontiguousarray(np.asarray(forces, np.float64)).tobytes())
    h.update(str(np.shape(forces)).encode())
    opts = {k: np.asarray(v).tolist() if v is not None else None for k, v in kwargs.items()}
    h.update(json.dumps([tol, float(max_sim_dt), opts], sort_keys=True, default=str).encode())
    return os.path.join(root, _cache_tag(), "steps", h.hexdigest() + ".json")


def _read_step_cache(path):
    import json

    if path is None:
        return None
    try:
        with open(path) as f:
            rec = json.load(f)
        return int(rec["substeps"]), float(rec["estimated_error"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _write_step_cache(path, substeps, err) -> None:
    import json
    import os

    if path is None:
        return
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        tmp = f"{path}.{os.getpid()}.tmp"
        with open(tmp, "w") as f:
            json.dump({"substeps": int(substeps), "estimated_error": float(err)}, f)
        os.replace(tmp, path)
    except OSError:  # a read-only cache folder: the choice is simply recomputed next time
        pass
