"""Evaluation of a posterior: predictions of every particle with their band, per-trajectory
log-likelihood, held-out metrics, k-fold splits and the metrics' mean over folds.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..data.trajectories import (
    Observations,
    Trajectory,
    stack_trajectories,
)
from ..errors import ConfigError, SimulationError
from ..io.jsonio import write_json

LEVEL = 0.95  # credible / predictive interval mass everywhere in the run folder


# ==== predictions =================================================================================
class Prediction(NamedTuple):
    """Posterior predictive rollouts: ``tau [P, B, T]`` m; ``valid [P]`` particles used (stable
    here and finite posterior density); ``lower``, ``upper``, ``mean`` ``[B, T]`` m: the
    PARAMETER band (95% KDE of the simulations, no noise). ``predictive_lower``,
    ``predictive_upper`` ``[B, T]`` m: the PREDICTIVE band (simulations + the fitted noise model,
    never zero-width), None when no noise level is known; ``sigma`` the noise scale used
    (scalar or ``[P]`` m), ``noise_kind`` its distribution. ``force_variance`` ``[B, T]`` m^2
    (dynamic, :mod:`treeinfer.model.force_noise`) or ``[P, B, T]`` (static, each draw's own,
    :class:`treeinfer.inference.static.StaticForceNoise`): the force-noise-induced variance the
    predictive band adds to every point (runs with ``--noise-force``; from the predicted
    recording's own force), else None."""

    tau: np.ndarray
    tau_dot: np.ndarray
    stable: np.ndarray
    valid: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    mean: np.ndarray
    predictive_lower: np.ndarray | None = None
    predictive_upper: np.ndarray | None = None
    sigma: np.ndarray | float | None = None
    noise_kind: str = "gaussian"
    force_variance: np.ndarray | None = None

    def band(self):
        """``(lower, upper)`` to compare recordings with: predictive if known, else parameter."""
        if self.predictive_lower is not None:
            return self.predictive_lower, self.predictive_upper
        return self.lower, self.upper


def noise_for(theta, n_joints: int, settings: dict | None):
    """``(sigma, kind)`` of a run's noise model for its predictive band: per-particle sigma from
    theta's noise columns, else the recorded fixed or estimated ``noise_displacement`` (m),
    else ``(None, "gaussian")`` (runs from before issue 11 without an estimate)."""
    from ..model.likelihood import noise_params_from_theta, predictive_noise_kind

    settings = settings or {}
    kind = predictive_noise_kind(settings.get("likelihood", "boltzmann"))
    fixed = settings.get("noise_displacement")
    theta = np.atleast_2d(np.asarray(theta))
    k = int(settings.get("channel_noise_columns", 0))  # observation channels' sigma, last
    if k:
        theta = theta[:, :-k]
    if settings.get("kp_shape") is not None:  # a tied layout: one scale (+ R deviations), noise
        from ..inference.static.tied import tied_noise_theta

        theta = tied_noise_theta(theta, n_joints, settings)
    elif list(settings.get("parameters", ["kp", "kd"])) == ["kp"]:  # stiffness only: pad Kd
        theta = np.insert(theta, [n_joints] * n_joints, 0.0, axis=1)
    try:
        sigma = noise_params_from_theta(theta, n_joints, fixed)
    except ConfigError:
        sigma = None
    floor = (settings.get("integration_error") or {}).get("rms_m")
    if sigma is not None and floor:  # the simulator's own error (model/integration_error.py):
        # the band's rollouts are not corrected for it, so it is part of every point's spread
        sigma = np.hypot(np.asarray(sigma, float), float(floor))
    return (None if sigma is None else np.asarray(sigma, float)), kind


def force_noise_for(settings: dict | None):
    """The run's force-noise term from its problem settings, else None: for the paper's dynamic
    model a :class:`treeinfer.model.force_noise_model.ForceNoiseModel` (``noise_force`` N and
    ``noise_force_reference``, written by runs with ``--noise-force``); for ``--model-kind
    static`` runs with ``--noise-force`` a :class:`treeinfer.inference.static.StaticForceNoise`
    (``force_noise`` N: the load cell's noise read through each draw's compliance, as in the
    run's likelihood)."""
    from ..inference.static import static_force_noise_for
    from ..model.force_noise_model import ForceNoiseModel

    static = static_force_noise_for(settings)
    if static is not None:
        return static
    settings = settings or {}
    sf, ref = settings.get("noise_force"), settings.get("noise_force_reference")
    if sf is None or ref is None:
        return None
    grasp = settings.get("grasp_fraction")
    return ForceNoiseModel(
        float(sf),
        np.asarray(ref, float),
        str(settings.get("noise_force_rule", "")),
        None if isinstance(grasp, (list, tuple)) else grasp,
    )


def predict_run(
    sim,
    theta,
    forces,
    grasp_fraction=None,
    particle_ok=None,
    level: float = LEVEL,
    noise_sigma=None,
    noise_kind: str = "gaussian",
    model=None,
    force_noise=None,
    traced_substeps: bool = False,
    rollout=None,
) -> Prediction:
    """Simulate every particle ``theta [P, D]`` under ``forces [B, T]`` and summarise the bands
    (parameter band; predictive band too when ``noise_sigma``, scalar or ``[P]`` m, is given);
    unstable particles are excluded (``valid``). Needs two valid particles. ``model``: the
    run's :class:`treeinfer.inference.static.Model` (None: the dynamic model of ``[log Kp, log
    Kd]``). ``force_noise``: the run's force-noise term (:func:`force_noise_for`): the forces are
    taken as recorded (noisy), and the predictive band adds the variance that noise induces
    (dynamic: ``diag C`` of each pull at the run's reference gains, ``force_variance [B, T]``;
    static: each draw's own ``(sigma_F c_p)^2``, ``force_variance [P, B, T]``). ``traced_substeps``:
    as in :func:`treeinfer.inference.problem.predict`. ``rollout``: the
    :class:`treeinfer.sim.Rollout` of ``theta`` under ``forces`` when the caller has it (the
    run's training fit, from the start pipeline's program), else simulated here."""
    from ..inference.rollout import predict
    from .metrics import noisy_predictive_interval, predictive_interval

    theta = np.atleast_2d(np.asarray(theta))
    # the gain columns only: a run's noise columns (sigma_x, ... and one per observation
    # channel's sensor, any number) never enter the simulation
    theta = theta[:, : (2 * sim.n_joints if model is None else model.layout.dim)]
    if rollout is None:
        rollout = predict(
            sim,
            theta,
            np.atleast_2d(np.asarray(forces, np.float32)),
            grasp_fraction,
            model=model,
            traced_substeps=traced_substeps and model is None,
        )
    rollout = jax.device_get(rollout)
    stable = np.asarray(rollout.stable).all(axis=-1)
    valid = stable & (
        np.ones(len(theta), bool) if particle_ok is None else np.asarray(particle_ok, bool)
    )
    if valid.sum() < 2:
        raise SimulationError(
            f"only {int(valid.sum())} of {len(theta)} particles give a stable simulation of "
            "these forces; a predictive band needs at least 2 (are the forces far larger than "
            "in training?)"
        )
    tau = np.asarray(rollout.tau)
    lower, upper, mean = (np.asarray(a) for a in predictive_interval(tau, level, valid))
    plo = phi = fvar = None
    if noise_sigma is not None and force_noise is not None:
        from ..inference.static import StaticForceNoise

        if isinstance(force_noise, StaticForceNoise):  # each draw's compliance at each pull
            if model is None or model.kind != "static":
                raise ConfigError("the load-cell term of a static run needs its static model")
            fvar = force_noise.point_variance(np.where(valid[:, None, None], tau, 0.0), forces)
        elif model is None:
            from ..model.force_noise import point_variance

            fmodel = force_noise._replace(grasp_fraction=grasp_fraction)  # the predicted pulls'
            fvar = point_variance(fmodel.basis(sim, np.atleast_2d(np.asarray(forces, float))))
    if noise_sigma is not None:
        plo, phi, _ = (
            np.asarray(a)
            for a in noisy_predictive_interval(
                tau, noise_sigma, level, valid, noise_kind, extra_variance=fvar
            )
        )
    return Prediction(
        tau,
        np.asarray(rollout.tau_dot),
        stable,
        valid,
        lower,
        upper,
        mean,
        plo,
        phi,
        noise_sigma,
        noise_kind,
        fvar,
    )


def rollout_loglik(rollout, obs: Observations, kT: float, ok=None, dtype=None) -> np.ndarray:
    """[P, B] Boltzmann log-likelihood ``-loss / kT`` of each particle's rollout [P, B, T] on each
    trajectory of ``obs``; -inf where ``ok`` (default ``rollout.stable`` [P, B]) is False.
    ``dtype``: of the loss before scaling (default: the simulator's)."""
    from ..model.boltzmann import trajectory_loss

    loss = np.asarray(trajectory_loss(rollout, obs), dtype)
    return np.where(np.asarray(rollout.stable) if ok is None else ok, -loss / kT, -np.inf)


def _per_trajectory_loglik(pred: Prediction, obs: Observations, kT: float) -> np.ndarray:
    """[P, B] Boltzmann log-likelihood of each particle on each trajectory (-inf if unstable)."""
    from ..sim import Rollout

    stable = jnp.asarray(np.broadcast_to(pred.stable[:, None], pred.tau.shape[:2]))
    r = Rollout(jnp.asarray(pred.tau), jnp.asarray(pred.tau_dot), stable)
    return rollout_loglik(r, obs, kT, ok=pred.valid[:, None])


def evaluate_trajectories(
    sim,
    theta,
    labels,
    trajectories: Sequence[Trajectory],
    kT: float,
    grasp_fraction=None,
    truth=None,
    particle_ok=None,
    noise_sigma=None,
    noise_kind: str = "gaussian",
    model=None,
    force_noise=None,
) -> tuple[dict, Prediction, Observations]:
    """Held-out metrics of particles ``theta`` on ``trajectories``
    (:func:`treeinfer.evaluation.metrics.summarize` with the posterior NLL of the held-out data,
    per-trajectory CI width / % outside and, with ``truth [2R]`` in natural units,
    posterior vs truth in log space)."""
    from .metrics import ci_width, fraction_outside, summarize

    obs = stack_trajectories(list(trajectories))
    if not math.isclose(float(obs.dt), sim.obs_dt, rel_tol=1e-6):
        raise ConfigError(
            f"the trajectories have dt={obs.dt:g} s but the run was inferred at "
            f"dt={sim.obs_dt:g} s; resample them to the run's step"
        )
    pred = predict_run(
        sim,
        theta,
        obs.force,
        grasp_fraction,
        particle_ok,
        noise_sigma=noise_sigma,
        noise_kind=noise_kind,
        model=model,
        force_noise=force_noise,
    )
    ll = _per_trajectory_loglik(pred, obs, kT)
    n_gains = 2 * sim.n_joints if model is None else model.layout.dim  # noise: no true value
    if truth is not None:  # stiffness only: theta holds the first D of the 2R true gains
        truth = np.asarray(truth, float)[:n_gains]
    m = summarize(
        pred.tau,
        obs.displacement,
        mask=obs.mask,
        valid=pred.valid,
        log_likelihood=ll,
        particles=None if truth is None else np.exp(np.asarray(theta, float)[:, :n_gains]),
        truth=truth,
        labels=None if labels is None else list(labels)[:n_gains],
        log_space=True,
        noise_sigma=noise_sigma,
        noise_kind=noise_kind,
        extra_variance=pred.force_variance,
    )
    if pred.force_variance is not None:
        m["band_includes_force_noise"] = True  # the predictive band: + diag C of each force
    lo_b, hi_b = pred.band()
    m["per_trajectory"] = [
        {
            "name": t.source,
            "ci_width": float(ci_width(lo_b[b], hi_b[b], obs.mask[b])),
            "pct_outside": 100.0
            * float(fraction_outside(lo_b[b], hi_b[b], obs.displacement[b], obs.mask[b])),
        }
        for b, t in enumerate(trajectories)
    ]
    m["units"] = {
        "ci_width": "m",
        "predictive_nll": "nats",
        "posterior_nll": "nats (kT-scaled loss)",
    }
    return m, pred, obs


# ==== k-fold cross-validation =====================================================================
def kfold_splits(n: int, k: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``k`` (train, test) index splits of ``n`` items: contiguous folds in file order, sizes
    differing by at most one (``numpy.array_split``)."""
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 2:
        raise ConfigError(f"--kfold: K must be an integer >= 2, got {k!r}")
    if k > n:
        raise ConfigError(
            f"--kfold {k}: needs at least {k} trajectories (one held-out fold each), found {n}"
        )
    idx = np.arange(n)
    folds = np.array_split(idx, k)
    return [(np.setdiff1d(idx, f), f) for f in folds]


def mean_metrics(results: Sequence[dict]) -> tuple[dict, dict]:
    """Mean and standard deviation (ddof=0) over folds of every numeric top-level metric."""
    keys = [
        k for k, v in results[0].items() if isinstance(v, (int, float)) and not isinstance(v, bool)
    ]
    mean, std = {}, {}
    for k in keys:
        vals = np.array(
            [r[k] for r in results if isinstance(r.get(k), (int, float)) and r.get(k) is not None],
            float,
        )
        mean[k] = float(np.mean(vals)) if vals.size else None
        std[k] = float(np.std(vals)) if vals.size else None
    return mean, std


# ==== evaluation output ===========================================================================
def band_arrays(preds_and_obs) -> tuple[np.ndarray, ...]:
    """Stack (prediction, obs) pairs of possibly different lengths into [K, T] arrays (NaN padded):
    the band compared with recordings (:meth:`Prediction.band`: predictive when known)."""
    rows = [
        (
            pr.band()[0][b],
            pr.band()[1][b],
            pr.mean[b],
            np.where(ob.mask[b], ob.displacement[b], np.nan),
            ob.mask[b],
        )
        for pr, ob in preds_and_obs
        for b in range(ob.force.shape[0])
    ]
    t_max = max(len(r[0]) for r in rows)
    out = np.full((5, len(rows), t_max), np.nan)
    for k, r in enumerate(rows):
        for j, a in enumerate(r):
            a = np.where(r[4], a, np.nan) if j < 4 else a
            out[j, k, : len(a)] = a
    return out[0], out[1], out[2], out[3]


def write_evaluation(
    out: Path,
    metrics: dict,
    bands,
    titles: Sequence[str],
    dt: float,
    config: dict,
    force: bool,
    md: Sequence[str],
    extra_files: dict[str, str] | None = None,
    formats=("png",),
) -> None:
    """metrics.json, metrics.md, bands.png, config.json (+ extra text files) in a staged folder;
    ``formats``: the figure's file formats (``png``, ``pdf``, ``svg``)."""
    from ..io.atomic import atomic_write_text, staged_output_dir
    from .plots import plot_band_grid, save_figure

    lower, upper, mean, gt = bands
    m = metrics.get("metrics") or metrics.get("mean") or {}
    which = (
        "95% predictive band (simulation + fitted noise)"
        if m.get("band") == "predictive"
        else "95% parameter band (simulations only, no noise)"
    )
    inputs = [p for p in (config.get("run"), *(config.get("inputs") or ())) if p]
    with staged_output_dir(out, force, "evaluation", inputs=inputs) as stage:
        write_json(stage / "metrics.json", metrics)
        atomic_write_text(stage / "metrics.md", "\n".join(md))
        t = np.arange(lower.shape[1]) * dt
        fig, _ = plot_band_grid(
            t,
            np.nan_to_num(lower),
            np.nan_to_num(upper),
            mean,
            gt,
            titles=list(titles),
            suptitle=f"{which} vs held-out recordings",
            reference_label="recording",
        )
        save_figure(fig, stage / "bands.png", formats=formats)
        write_json(stage / "config.json", config)
        for name, text in (extra_files or {}).items():
            atomic_write_text(stage / name, text)
