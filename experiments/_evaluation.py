"""Predictions, metrics, predictive bands and figures of the studies (split from
:mod:`experiments.common`)."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as `python experiments/<study>.py` from anywhere
    sys.path.insert(0, str(ROOT))

from experiments._config import StudyConfig  # noqa: E402
from experiments._data import SyntheticData  # noqa: E402
from experiments._posterior_cache import PosteriorRun  # noqa: E402
from treeinfer.errors import ConfigError, SimulationError


# ==== evaluation ==================================================================================
class Predictions(NamedTuple):
    """Rollouts of every particle on the training and the test forces.

    train_tau: [P, n_train, T]; test_tau: [P, n_test, T] m. valid: [P] stable on all of them.
    train_loglik: [P, n_train] Boltzmann log-likelihood ``-L_b / kT`` of each training trajectory
    (-inf for an unstable particle); with a generative likelihood [P, 1], the problem's whole
    training log-likelihood (noise model included). noise_sigma: [P] m marginal displacement
    noise of each particle (generative likelihoods; None for Boltzmann) and noise_kind its
    distribution: the predictive band adds this noise to the simulations."""

    train_tau: np.ndarray
    test_tau: np.ndarray
    valid: np.ndarray
    train_loglik: np.ndarray
    noise_sigma: np.ndarray | None = None
    noise_kind: str = "gaussian"


def _generative(problem) -> bool:
    noise = getattr(problem, "noise", None)
    return noise is not None and noise.settings.get("likelihood", "boltzmann") != "boltzmann"


def predict_all(problem, theta: np.ndarray, data: SyntheticData) -> Predictions:
    """One batched prediction of ``theta`` on the training and test forces (one compiled shape
    per size: the grasp fraction is always passed per profile)."""
    from treeinfer.evaluation import rollout_loglik
    from treeinfer.inference.problem import predict
    from treeinfer.model.likelihood import noise_params_from_theta, predictive_noise_kind
    from treeinfer.sim import Rollout

    n_train = len(data.train)
    n_gains = len(data.theta)  # 2R: theta may carry noise columns after the gains
    forces = np.stack([t.force for t in data.train + data.test])
    grasp = np.concatenate([np.full(n_train, data.tree.grasp_fraction), data.test_grasp])
    r = predict(data.sim, np.asarray(theta)[:, :n_gains], forces, grasp_fraction=grasp)
    tau, tau_dot, stable = (np.asarray(a) for a in (r.tau, r.tau_dot, r.stable))
    valid = stable.all(axis=1)
    if not _generative(problem):
        train = Rollout(tau[:, :n_train], tau_dot[:, :n_train], stable[:, :n_train])
        ll = rollout_loglik(train, problem.obs, problem.kT, dtype=float)
        return Predictions(tau[:, :n_train], tau[:, n_train:], valid, ll)
    noise = problem.noise
    kind = predictive_noise_kind(noise.settings["likelihood"])
    sigma = np.asarray(noise_params_from_theta(theta, n_gains // 2, noise.sigma_x), float)
    ll = np.asarray(problem.log_likelihood(np.asarray(theta, np.float32)), float)[:, None]
    ll = np.where(valid[:, None] & np.isfinite(ll), ll, -np.inf)
    return Predictions(tau[:, :n_train], tau[:, n_train:], valid, ll, sigma, kind)


def metrics_for(
    pred: Predictions, theta: np.ndarray, data: SyntheticData, problem, cfg: StudyConfig, idx=None
) -> dict:
    """The paper's metrics on test trajectories ``idx`` (default all) plus the posterior against the
    truth, as :func:`treeinfer.evaluation.summarize` reports them; ``{"error": ...}`` when fewer
    than two particles simulate stably (no predictive distribution)."""
    from treeinfer.evaluation import summarize

    idx = np.arange(len(data.test)) if idx is None else np.asarray(idx)
    gt = np.stack([data.test[i].displacement for i in idx])
    try:
        m = summarize(
            pred.test_tau[:, idx],
            gt,
            valid=pred.valid,
            level=cfg.level,
            log_likelihood=pred.train_loglik,
            particles=None,
            truth=None,
            noise_sigma=pred.noise_sigma,
            noise_kind=pred.noise_kind,
        )
        theta_ok = pred.valid & np.all(np.isfinite(pred.train_loglik), axis=1)
        m.update(parameter_metrics(problem, theta, data, cfg, theta_ok))
    except (SimulationError, ConfigError) as e:
        return {
            "error": str(e),
            "n_valid_particles": int(pred.valid.sum()),
            "n_particles": int(pred.valid.size),
        }
    m["n_test_trajectories"] = len(idx)
    m["n_train_trajectories"] = len(data.train)
    m["posterior_nll_per_point"] = m["posterior_nll"] / float(
        pred.train_tau.shape[1] * pred.train_tau.shape[2]
    )
    return m


def interval_metrics(pred: Predictions, gt: np.ndarray, cfg: StudyConfig) -> dict:
    """CI width, % outside and predictive NLL of the test predictions against another ground
    truth ``gt [n_test, T]`` (e.g. the noise-free displacement in the noise study)."""
    from treeinfer.evaluation import summarize

    try:
        m = summarize(
            pred.test_tau,
            gt,
            valid=pred.valid,
            level=cfg.level,
            noise_sigma=pred.noise_sigma,
            noise_kind=pred.noise_kind,
        )
    except (SimulationError, ConfigError) as e:
        return {"error": str(e)}
    keys = (
        "ci_width",
        "pct_outside",
        "fraction_outside",
        "predictive_nll",
        "predictive_nll_per_point",
        "n_points",
    )
    return {k: m[k] for k in keys}


def parameter_metrics(
    problem, theta: np.ndarray, data: SyntheticData, cfg: StudyConfig, valid
) -> dict:
    """Posterior ``theta [P, D]`` vs the truth in log space (``parameters``,
    ``truth_in_joint_region``, ``mean_abs_log_error``, ``n_params_in_interval``)."""
    from treeinfer.evaluation import posterior_vs_truth

    n_gains = len(data.theta)  # the noise columns of a generative likelihood have no truth
    theta = np.asarray(theta)[:, :n_gains]
    chk = posterior_vs_truth(theta, data.theta, cfg.level, valid)  # theta is already ln K
    labels = list(problem.labels)[:n_gains]
    params = {
        lab: {
            "mean": float(chk.mean[i]),
            "truth": float(data.theta[i]),
            "abs_error": float(chk.abs_error[i]),
            "lower": float(chk.lower[i]),
            "upper": float(chk.upper[i]),
            "in_interval": bool(chk.in_marginal[i]),
        }
        for i, lab in enumerate(labels)
    }
    return {
        "parameters": params,
        "parameter_space": "log",
        "truth_in_joint_region": chk.in_joint,
        "mean_abs_log_error": float(np.mean(chk.abs_error)),
        "n_params_in_interval": int(np.sum(chk.in_marginal)),
        "n_params": len(labels),
    }


def evaluate(
    problem, run: PosteriorRun, data: SyntheticData, cfg: StudyConfig, groups: dict | None = None
) -> tuple[Predictions, dict]:
    """Predict with the posterior and compute the metrics, over all test trajectories or per group
    (``{name: test indices}``, e.g. per grasp location)."""
    pred = predict_all(problem, run.theta, data)
    if groups is None:
        return pred, metrics_for(pred, run.theta, data, problem, cfg)
    return pred, {
        name: metrics_for(pred, run.theta, data, problem, cfg, idx) for name, idx in groups.items()
    }


def inference_record(run: PosteriorRun) -> dict:
    ld = run.log_density[np.isfinite(run.log_density)]
    return {
        "sampler_wall_s": run.elapsed_s,
        "from_cache": run.from_cache,
        "cache_key": run.key,
        "sampler_options": run.settings.get("sampler_options"),
        "n_particles": run.settings.get("n_particles"),
        "n_iterations": run.settings.get("n_iterations"),
        "final_mean_log_density": float(ld.mean()) if ld.size else None,
        "n_nonfinite_final": int(np.sum(~np.isfinite(run.log_density))),
    }


# ==== bands and plots =============================================================================
class Bands(NamedTuple):
    """Predictive bands of a few test trajectories: lower/upper/mean/gt [k, T], samples
    [k, S, T]."""

    lower: np.ndarray
    upper: np.ndarray
    mean: np.ndarray
    gt: np.ndarray
    samples: np.ndarray


def bands_for(
    pred: Predictions, data: SyntheticData, idx: Sequence[int], level: float, max_samples: int = 10
) -> Bands:
    from treeinfer.evaluation.metrics import predictive_interval

    idx = np.asarray(idx)
    gt = np.stack([data.test[i].displacement for i in idx])
    tau = pred.test_tau[:, idx]
    if pred.valid.sum() >= 2:
        lo, hi, mean = (np.asarray(a, float) for a in predictive_interval(tau, level, pred.valid))
        samples = np.moveaxis(tau[pred.valid][:max_samples], 0, 1)
    else:  # no predictive distribution: draw the ground truth alone
        lo = hi = mean = np.full(gt.shape, np.nan)
        samples = np.full((len(idx), 1, gt.shape[-1]), np.nan)
    return Bands(lo, hi, mean, gt, samples)


def band_grid(
    rows: dict[str, Bands],
    dt: float,
    level: float,
    col_labels: Sequence[str],
    title: str,
    transpose: bool = False,
):
    """Rows = conditions, columns = test trajectories (paper Fig. 3/5 layout); ``transpose``
    puts the conditions in columns instead (Fig. 6: one column per grasp location)."""
    from treeinfer.evaluation import plot_band_grid

    names = list(rows)
    stack = lambda f: np.stack([getattr(rows[n], f) for n in names])
    arrays = [stack(f) for f in ("lower", "upper", "mean", "gt", "samples")]
    row_labels, col_labels = names, list(col_labels)
    if transpose:
        arrays = [np.swapaxes(a, 0, 1) for a in arrays]
        row_labels, col_labels = col_labels, row_labels
    t = np.arange(arrays[0].shape[-1]) * dt
    fig, _ = plot_band_grid(
        t,
        *arrays,
        row_labels=row_labels,
        col_labels=col_labels,
        suptitle=title,
        ylabel=f"displacement [m] ({level:.0%} band, grey)",
    )
    return fig


def metric_figure(names: Sequence[str], conditions: Sequence[dict], title: str, keys=None):
    """Bars of CI width, % GT outside and predictive NLL per condition (NaN for failed ones)."""
    from treeinfer.evaluation.plots import metric_bars

    keys = keys or {
        "95% CI width [m]": "ci_width",
        "% GT outside": "pct_outside",
        "NLL / test point [nats]": "predictive_nll_per_point",
    }
    values = {
        lab: [c.get(k, np.nan) if "error" not in c else np.nan for c in conditions]
        for lab, k in keys.items()
    }
    fig, _ = metric_bars(list(names), values, separate=True, title=title)
    return fig


def pair_figure(sets: dict[str, np.ndarray], labels: Sequence[str], truth: np.ndarray, title: str):
    """Pair plot of log-parameter particles of several posteriors with the truth (paper Fig. 4)."""
    from treeinfer.evaluation.plots import pair_plot

    fig, _ = pair_plot(sets, [f"ln {lab}" for lab in labels], truth, title=title)
    return fig
