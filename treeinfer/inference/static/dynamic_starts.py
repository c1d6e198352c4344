"""The dynamic model's starts on a quasi-static pull with observation channels: the static
(stiffness-only) model first.

A tree pulling test (a winch ramp over tens of seconds, inclinometers on the stem) is a sequence
of near-equilibria: its slow force fixes the stiffnesses and hardly touches the damping. The
dynamic model's own starts, random in its ``2R + noise``-dimensional box, miss that mode: on
the worked example of ``docs/pulling_tests.md`` its MAP fit ended with every Kp at 4-30x the
box's edge and the misfit called noise (``infer`` said ``poor_fit``, exit 4). So, as a pulling
test is analysed by hand, the stiffnesses come first: :func:`static_first_starts` fits the
static model (equilibrium under each force sample, the same channels, every noise scale
inferred) by its MAP and Laplace covariance, and builds the dynamic fit's starts from it: Kp and
the noise scales from the static MAP and draws of its Laplace approximation, damping at
:data:`KD_LEVELS` across its prior box. The start pipeline screens them with its random starts
under the dynamic model's own log-density (:func:`treeinfer.inference.laplace.problem_laplace`),
so a poor static seed costs nothing but its fit.

The data are a *quasi-static pull* (:func:`quasi_static_pull`) when the force's slowest rise
(from 10% to 90% of its peak, per pull) lasts at least :data:`RISE_PERIODS` of the tree's
slowest natural period at the centre of the stiffness prior (the judgement of
:func:`treeinfer.inference.static.quasi_static_notice`, about the force rather than the sample
interval: a 10 Hz record of a slow ramp is quasi-static in its force, not in its sampling).
"""

from __future__ import annotations

import math

import numpy as np

from ...data.types import Trajectory
from ...errors import ConfigError, SimulationError
from .detection import natural_periods

RISE_PERIODS = 5.0  # the force's rise / the slowest natural period, above which a pull is slow
KD_LEVELS = (0.2, 0.35, 0.5, 0.65, 0.8)  # damping starts: fractions across its log box
N_STATIC = 8  # static seeds: its MAP and N_STATIC - 1 draws of its Laplace approximation


def force_rise_time(force: np.ndarray, mask: np.ndarray, dt: float) -> float:
    """s, the shortest rise of the force from 10% to 90% of its largest magnitude over the
    pulls (``force``, ``mask`` ``[B, T]``); inf for a pull whose force never leaves zero."""
    rises = []
    for f, m in zip(np.abs(np.asarray(force, float)), np.asarray(mask, bool)):
        f = f[m]
        peak = float(f.max()) if f.size else 0.0
        if not peak > 0:
            continue
        i10 = int(np.argmax(f >= 0.1 * peak))
        i90 = int(np.argmax(f >= 0.9 * peak))
        rises.append(max(i90 - i10, 1) * float(dt))
    return min(rises) if rises else math.inf


def quasi_static_pull(problem) -> str | None:
    """A message when ``problem`` is the dynamic model (Kp and Kd inferred) of a quasi-static
    pull with observation channels (module docstring), else None."""
    model = problem.model
    layout_ok = model is None or (model.kind == "dynamic" and model.layout.infers_damping)
    if not (layout_ok and problem.settings.get("channels")):
        return None
    if model is not None and getattr(model.layout, "shape", None) is not None:
        return None  # a tied layout: its static counterpart has other columns
    tree = problem.tree
    lo, hi = tree.bounds_array()
    r = tree.n_inferred
    try:
        slowest = float(natural_periods(problem.sim, np.sqrt(lo[:r] * hi[:r]))[0])
    except Exception:  # noqa: BLE001 - a judgement must never stop a run: no static start
        return None
    rise = force_rise_time(problem.obs.force, problem.obs.mask, float(problem.obs.dt))
    if not (math.isfinite(slowest) and rise >= RISE_PERIODS * slowest):
        return None
    return (
        f"quasi-static pull: the force rises over {rise:.3g} s, {rise / slowest:.0f}x the "
        f"tree's slowest natural period ({slowest:.3g} s at the prior's centre)"
    )


def recordings(problem) -> list[Trajectory] | None:
    """The problem's pulls as trajectories named as its channels name them, or None when that
    cannot be told from the problem (it keeps the stacked observations only).

    The channels name their pulls by file name; the rows are the pulls in file-name order (as
    ``infer`` reads a data folder) when every pull has a channel; each pull starts at its
    channels' first sample (a channel's samples lie inside its pull: at most one sample
    interval off, which a slow pull does not notice, and only the static seed sees it)."""
    obs = problem.obs
    chans = problem.spec.channels if problem.spec is not None else ()
    names = sorted({c.recording for c in chans})
    mask = np.asarray(obs.mask, bool)
    if not chans or len(names) != mask.shape[0]:
        return None
    dt = float(obs.dt)
    out = []
    for b, name in enumerate(names):
        mine = [c for c in chans if c.recording == name]
        t0 = min(float(np.min(c.time)) for c in mine)
        n = int(mask[b].sum())
        end = max(float(np.max(c.time)) for c in mine)
        if end > t0 + n * dt:  # the channels outlast the row: the order guessed is wrong
            return None
        t = t0 + dt * np.arange(n)
        f, x = np.asarray(obs.force[b, :n], float), np.asarray(obs.displacement[b, :n], float)
        out.append(Trajectory(t, f, x, None, name))
    return out


def static_problem(problem, trajectories):
    """The static model of ``problem``'s data: same tree, pulls, channels and likelihood, the
    stiffness only (its default force-noise term, as ``infer --model-kind static``)."""
    from ..problem import make_problem
    from .model import model_for

    spec = problem.spec
    model = spec.model
    static = None
    if model is not None:
        static = model_for(problem.tree, "static", model.direction, model.grasp_branch)
    spec = spec.replace(model_kind="static", model=static, shape_bucket=None, noise_force="default")
    return make_problem(problem.tree, trajectories, spec, sim=problem.sim)


def dynamic_from_static(problem, static, theta_static: np.ndarray) -> np.ndarray:
    """``[N * len(KD_LEVELS), D]`` starts of ``problem`` (the dynamic model) from static
    particles ``theta_static [N, D_s]``: columns matched by label (Kp, the noise scales), Kd
    at :data:`KD_LEVELS` across its box (the same level for every joint), any other column at
    its box's centre."""
    labels, s_labels = list(problem.labels), list(static.labels)
    lo, hi = np.asarray(problem.lower, float), np.asarray(problem.upper, float)
    out = []
    for row in np.atleast_2d(theta_static):
        for u in KD_LEVELS:
            x = 0.5 * (lo + hi)
            for j, lab in enumerate(labels):
                if lab in s_labels:
                    x[j] = row[s_labels.index(lab)]
                elif lab.startswith("Kd["):
                    x[j] = lo[j] + u * (hi[j] - lo[j])
            out.append(np.clip(x, lo, hi))
    return np.asarray(out)


def static_first_starts(problem, seed: int = 0, log=lambda m: None) -> np.ndarray | None:
    """Start points of the dynamic model on a quasi-static pull with channels (module
    docstring), or None (not such a pull, or its pulls cannot be told apart: the start
    pipeline's own starts)."""
    from ..laplace import problem_laplace

    why = quasi_static_pull(problem)
    if why is None:
        return None
    trajs = recordings(problem)
    if trajs is None:
        log(f"{why}; its pulls cannot be matched to their channels: no static start")
        return None
    try:
        static = static_problem(problem, trajs)
        lap = problem_laplace(static, seed=seed)
    except (ConfigError, SimulationError, np.linalg.LinAlgError) as e:
        # e.g. an option the static model does not take (--noise-velocity): its own starts
        log(f"{why}; the static model could not be fitted ({e}): no static start")
        return None
    rng = np.random.default_rng(seed)
    chol = np.linalg.cholesky(lap.cov + 1e-12 * np.eye(len(lap.cov)))
    draws = lap.theta + rng.standard_normal((N_STATIC - 1, len(lap.theta))) @ chol.T
    theta = np.vstack([lap.theta, draws])
    kp = ", ".join(
        f"{lab} {math.exp(v):.3g}" for lab, v in zip(static.labels, lap.theta) if lab[:3] == "Kp["
    )
    log(
        f"{why}: the static model first (MAP {kp}; {lap.n_evals} evaluations); the dynamic "
        f"fit starts from it, damping across its prior"
    )
    return dynamic_from_static(problem, static, theta)
