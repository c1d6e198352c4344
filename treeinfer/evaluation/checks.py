"""Plausibility checks before inference and fit checks after it: never a confident wrong answer.

Before inference, :func:`data_checks` looks at the tree and the training trajectories together
and returns :class:`Finding` s (``error`` where the data are certainly wrong, ``warning`` where
they are suspicious), each naming the file and the evidence:

- **scale**: the quasi-static compliance of the data (least-squares slope of displacement on
  force, m/N) against what the tree can do with its inferred joints anywhere in the prior box
  (:func:`static_compliance`, a lever-arm estimate, see below): centimetres or millimetres read
  as metres, kilonewtons read as newtons, or a stiffness outside the prior box show up as a
  compliance 10-1000x outside that range;
- **mixed units** between files (one file's compliance far from the others');
- **swapped columns** (the inverse hypothesis fits the tree where the recorded one cannot);
- **sign**: displacement that moves against the force;
- **reach**: displacement larger than the grasp point can move at all;
- **rest**: displacement that does not start near zero while the force does;
- **velocity**: a recorded velocity column that does not integrate to the displacement
  (negated, zero, random, or in other units);
- **time unit**: the displacement moving implausibly fast for a branch (time in minutes);
- **duplicates**: byte-identical files or identical arrays (the same evidence counted twice);
- **all-zero** force or displacement (the posterior would be the prior).

After inference, :func:`fit_checks` judges the training fit by posterior predictive checks
(:mod:`treeinfer.evaluation.ppc`): coverage of the predictive band (with the inferred noise),
standardised residuals (mean, scale, tails) and their autocorrelation ("model misfit:
residuals autocorrelated"); then posterior mass of the gains at a prior-box edge and a posterior
no narrower than the prior. A noise scale's position in its prior never decides it. It returns
a :class:`FitVerdict` with ``status`` one of ``ok | warning | poor_fit`` and the reasons; a run
whose bands cover its training data is never ``poor_fit``. The command line ends a
``poor_fit`` run with exit code 4 (:data:`POOR_FIT_EXIT_CODE`) unless ``--allow-poor-fit``.

Static compliance. A downward force ``f`` at the grasp point moves it ``f * C`` down once the
tree has settled, with ``C = s K^-1 s^T``: ``s`` the grasp site's Jacobian along gravity and
``K`` the joint stiffness matrix (springs plus gravity's geometric stiffness), both taken from
plain MuJoCo at the rest pose the branch sags to under its own weight
(:func:`static_compliance`). With stiff joints ``C`` reduces to the lever-arm sum
``sum_j s_j^2 / Kp_j`` (:func:`lever_arm_compliance`); with soft ones the sag changes the lever
arms several-fold, hence the settled form. Dynamics are left out: the flagged factors (3x to
1000x outside the prior box's range) are far beyond what a pull's inertia and damping change.
tests/test_checks.py checks ``C`` against settled MJX rollouts.
"""

from __future__ import annotations

import math
import os
import statistics
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from ..data.checks import (  # noqa: F401 -- re-exported: the old import path keeps working
    data_checks,
)
from ..errors import ConfigError
from ..tree.description import Tree
from ..tree.plausibility import (  # noqa: F401 -- re-exported: the old import path keeps working
    MAX_BRANCH_SPEED,
    MAX_SUBSTEPS,
    MIXED_RATIO,
    POOR_FIT_EXIT_CODE,
    REST_FORCE,
    REST_FRACTION,
    REST_MIN,
    SCALE_ERROR,
    SCALE_WARN,
    VELOCITY_MISMATCH,
    ZERO_ATOL,
    Finding,
    compliance_range,
    errors_of,
    format_findings,
    grasp_reach,
    lever_arm_compliance,
    response_range,
    simulation_cost_check,
    static_compliance,
)

__all__ = [
    "POOR_FIT_EXIT_CODE",
    "Finding",
    "FitVerdict",
    "data_checks",
    "errors_of",
    "fit_checks",
    "fit_verdict_from_run",
    "format_findings",
    "grasp_reach",
    "lever_arm_compliance",
    "noise_from_kT",
    "preflight",
    "simulation_cost_check",
    "static_compliance",
]


# ---- after inference -------------------------------------------------------------------------
def noise_from_kT(kT: float, n_steps: int, dt: float, omega2: float = 0.0) -> float:
    """Displacement noise sigma (m) for which :func:`treeinfer.model.likelihood.suggest_kT` gives
    ``kT``: its inverse, ``sigma = kT sqrt(T) / (1 + sqrt(2) dt omega2)``."""
    return float(kT) * math.sqrt(n_steps) / (1.0 + math.sqrt(2.0) * float(dt) * float(omega2))


class FitVerdict(NamedTuple):
    """``status``: ``ok``, ``warning`` or ``poor_fit``; ``reasons``: one sentence each;
    ``measures``: the numbers behind them (JSON-ready), for summary.json."""

    status: str
    reasons: list[str]
    measures: dict

    def as_dict(self) -> dict:
        return {
            "status": self.status,
            "reasons": list(self.reasons),
            "measures": dict(self.measures),
        }


EDGE_BAND = 0.05  # share of the log box width counted as "at the edge"
EDGE_SHARE = 0.5  # share of particles at/beyond one edge that is flagged
NO_EFFECT = 0.9  # posterior std / prior std (log space) above which the data had no effect


def is_noise_column(label: str) -> bool:
    """A noise model's column (``sigma_x``, ``sigma_c``, ``rho``): judged by the posterior
    predictive checks through the bands, never by where it falls in its prior box."""
    return label.startswith("sigma") or label == "rho"


def fit_checks(
    *,
    residuals=None,
    mask=None,
    noise_sigma: float | None = None,
    fraction_outside: float | None = None,
    level: float = 0.95,
    theta=None,
    lower=None,
    upper=None,
    labels: Sequence[str] | None = None,
    valid=None,
    standardised=None,
    noise_model: bool = True,
    recorded=None,
) -> FitVerdict:
    """Judge a finished run's training fit by posterior predictive checks
    (:mod:`treeinfer.evaluation.ppc`), plus where the gains' posterior sits in their prior box.

    Args:
      residuals: [B, T] m, recorded minus predictive mean (or None).
      mask: [B, T] bool, real samples. noise_sigma: m, the white noise scale the residuals are
        standardised by when ``standardised`` is not given (``residuals / noise_sigma``: the
        predictive spread's white part only).
      fraction_outside: share (0-1) of training points outside the ``level`` predictive band
        (None: from ``residuals / noise_sigma`` when both are given).
      standardised: per pull, the one-step standardised residuals
        (:func:`treeinfer.evaluation.ppc.standardised_residuals`).
      noise_model: False for the Boltzmann likelihood (coverage never gives ``poor_fit``;
        ``recorded`` [B, T] gives the explained-variance check instead).
      theta: [P, D] final particles in log space; lower, upper: [D] log prior box;
        labels: D names (noise columns, :func:`is_noise_column`, are not judged by the box);
        valid: [P] bool, particles to use.

    ``poor_fit`` comes from the bands failing to cover the data (generative likelihoods), from
    a Boltzmann fit that explains less than half the data's variance, or, only where no
    coverage was measured, from the gains' posterior beyond a prior-box bound or as wide as the
    prior. A run whose bands cover its data is at worst ``warning``.

    Returns:
      :class:`FitVerdict`.
    """
    from . import ppc as cf

    poor: list[str] = []
    warn: list[str] = []
    m: dict = {}
    r = None
    if residuals is not None:
        r = np.asarray(residuals, float)
        r = r.reshape(1, -1) if r.ndim == 1 else r
        mk = np.ones(r.shape, bool) if mask is None else np.asarray(mask, bool)
        ok = mk & np.isfinite(r)
        if noise_sigma is not None and noise_sigma > 0 and ok.any():
            rms = float(np.sqrt(np.mean(r[ok] ** 2)))
            m["residual_rms_m"], m["noise_sigma_m"] = rms, float(noise_sigma)
            m["residual_to_noise"] = rms / float(noise_sigma)
            if standardised is None:
                standardised = [r[b][ok[b]] / float(noise_sigma) for b in range(r.shape[0])]
            if fraction_outside is None and noise_model:
                zq = statistics.NormalDist().inv_cdf(0.5 + level / 2.0)
                fraction_outside = float(np.mean(np.abs(r[ok]) > zq * float(noise_sigma)))
    if fraction_outside is not None and not math.isfinite(fraction_outside):
        fraction_outside = None
    coverage_ok = None
    if standardised is not None or fraction_outside is not None:
        stats = cf.ppc_stats(standardised or [], fraction_outside)
        p, w, meas = cf.ppc_findings(stats, level, noise_model)
        if "residual_to_noise" in m and p:
            p = [
                f"{x} (training residuals RMS {m['residual_rms_m']:.3g} m, "
                f"{m['residual_to_noise']:.3g}x the noise scale)"
                for x in p
            ]
        poor += p
        warn += w
        m.update(meas)
        coverage_ok = fraction_outside is not None and not p and noise_model
    if not noise_model and r is not None and recorded is not None:
        ev = cf.explained_variance(r, recorded, mask)
        if ev is not None:
            m["explained_variance"] = ev
            msg = (
                f"the posterior-mean simulation explains {max(ev, 0.0):.0%} of the recorded "
                "displacement's variance"
            )
            if ev < cf.EXPLAINED_POOR:
                poor.append(msg + ": the model does not explain the data")
            elif ev < cf.EXPLAINED_WARN:
                warn.append(msg)
    if theta is not None and lower is not None and upper is not None:
        th = np.asarray(theta, float)
        lo, hi = np.asarray(lower, float), np.asarray(upper, float)
        ok = np.all(np.isfinite(th), axis=1)
        if valid is not None:
            ok &= np.asarray(valid, bool)
        labels = list(labels) if labels is not None else [f"theta[{j}]" for j in range(th.shape[1])]
        keep = [j for j, lab in enumerate(labels) if not is_noise_column(lab)]
        th, lo, hi = th[ok][:, keep], lo[keep], hi[keep]
        labels = [labels[j] for j in keep]
        # with the bands shown to cover the data, the box says something about the prior, not
        # about the fit: a warning
        box_poor = warn if coverage_ok else poor
        if len(th) >= 2 and labels:
            width = hi - lo
            prior_std = width / math.sqrt(12.0)  # uniform on the log box
            post_std = th.std(axis=0, ddof=1)
            ratio = post_std / prior_std
            m["posterior_to_prior_std"] = {lab: float(r) for lab, r in zip(labels, ratio)}
            at_lo = np.mean(th <= lo + EDGE_BAND * width, axis=0)
            at_hi = np.mean(th >= hi - EDGE_BAND * width, axis=0)
            med = np.median(th, axis=0)
            edge = {}
            for j, lab in enumerate(labels):
                for share, side, bound in ((at_lo[j], "lower", lo[j]), (at_hi[j], "upper", hi[j])):
                    if share >= EDGE_SHARE:
                        edge[lab] = side
                        beyond = med[j] < lo[j] if side == "lower" else med[j] > hi[j]
                        msg = (
                            f"{lab}: {share:.0%} of the posterior sits at or beyond the "
                            f"prior box's {side} bound ({math.exp(bound):.4g}; "
                            f"median {math.exp(med[j]):.4g}): the "
                            f"data may lie outside the prior; widen inference.prior"
                        )
                        (box_poor if beyond else warn).append(msg)
            m["at_prior_edge"] = edge
            flat = [lab for lab, r in zip(labels, ratio) if r > NO_EFFECT]
            if flat and len(flat) == len(labels):
                box_poor.append(
                    f"the posterior is as wide as the prior for every parameter (std ratio "
                    f"{float(ratio.min()):.2f}-{float(ratio.max()):.2f}): the data had no effect "
                    "(kT far too large, or no force/displacement signal?)"
                )
            elif flat:
                warn.append(
                    f"the data barely narrowed {', '.join(flat)} (posterior std > "
                    f"{NO_EFFECT:.0%} of the prior's)"
                )
    status = "poor_fit" if poor else "warning" if warn else "ok"
    return FitVerdict(status, poor + warn, m)


# ---- glue for the run layer ------------------------------------------------------------------
def preflight(
    tree: Tree,
    trajectories: Sequence,
    paths: Sequence | None = None,
    tree_file: str | os.PathLike | None = None,
    grasp_fraction: float | None = None,
) -> tuple[list[Finding], list[Finding]]:
    """(errors, warnings) of :func:`data_checks`, for ``infer`` to print before sampling: it
    stops with exit code 2 on errors, prints warnings and goes on."""
    found = data_checks(
        tree, trajectories, paths=paths, grasp_fraction=grasp_fraction, tree_file=tree_file
    )
    if trajectories:
        found += simulation_cost_check(tree, float(trajectories[0].dt), tree_file)
    return errors_of(found), [f for f in found if f.severity != "error"]


def fit_verdict_from_run(
    problem, posterior, fit: dict, noise_sigma: float | None = None, level: float = 0.95
) -> FitVerdict:
    """:func:`fit_checks` on what :func:`treeinfer.runs.run_inference` has at hand: posterior
    predictive checks on the training data (:mod:`treeinfer.evaluation.ppc`).

    Args:
      problem: the inference problem (``obs`` [B, T] training data, ``lower``/``upper`` log
        prior box [D], ``labels``; ``settings``, ``noise``, ``sim`` where it has them: the
        likelihood, its noise columns and force-noise term).
      posterior: ``theta`` [P, D].
      fit: the run's training fit: ``stable`` [P], ``prediction`` (``tau`` [P, B, T] draws,
        ``valid``, ``mean`` [B, T], ``sigma``: the noise scale per draw; None if too few
        particles were stable), ``metrics`` (``fraction_outside`` of the predictive band).
      noise_sigma: a white noise scale (m) to standardise by when the prediction carries none.
    """
    from ..model.noise import NOISE_KINDS
    from . import ppc as cf

    pred = fit.get("prediction")
    metrics = fit.get("metrics") or {}
    settings = getattr(problem, "settings", None) or {}
    kind = settings.get("likelihood")
    generative = kind in NOISE_KINDS or (kind is None and not settings and noise_sigma is not None)
    obs = problem.obs
    x = np.asarray(obs.displacement, float)
    mask = np.asarray(obs.mask, bool)
    residuals = standardised = None
    frac = metrics.get("fraction_outside")
    if pred is not None:
        residuals = x - np.asarray(pred.mean, float)
        tau = getattr(pred, "tau", None)
        if tau is not None:
            nvar, extra = _noise_covariance(problem, posterior, pred, generative, noise_sigma)
            if nvar is not None:
                standardised = cf.standardised_residuals(
                    x, tau, mask, nvar, extra, getattr(pred, "valid", None)
                )
        if not generative and getattr(pred, "sigma", None) is None:
            frac = None  # a parameter-only band (no noise level): its coverage says nothing
    verdict = fit_checks(
        residuals=residuals,
        mask=mask,
        noise_sigma=noise_sigma,
        fraction_outside=None if frac is None else float(frac),
        level=level,
        theta=np.asarray(posterior.theta, float),
        lower=problem.lower,
        upper=problem.upper,
        labels=list(problem.labels),
        valid=np.asarray(fit.get("stable"), bool) if fit.get("stable") is not None else None,
        standardised=standardised,
        noise_model=generative,
        recorded=x,
    )
    if pred is not None:
        align, meas = cf.alignment_findings(x, pred.mean, mask, float(obs.dt))
        verdict.measures.update(meas)
        if align:
            status = "warning" if verdict.status == "ok" else verdict.status
            verdict = FitVerdict(status, [*verdict.reasons, *align], verdict.measures)
    misfit = _misfit_called_noise(problem, posterior, verdict.measures) if generative else None
    if misfit is not None:
        verdict = FitVerdict("poor_fit", [*verdict.reasons, misfit[0]], verdict.measures)
        verdict.measures["misfit_called_noise"] = misfit[1]
    above = _noise_above_recording(problem, posterior) if generative and misfit is None else None
    if above is not None:
        status = "warning" if verdict.status == "ok" else verdict.status
        verdict = FitVerdict(status, [*verdict.reasons, above[0]], verdict.measures)
        verdict.measures["noise_above_recording"] = above[1]
    if pred is None:  # the unstable-share limit already judged this; do not fail twice
        status = verdict.status if verdict.status == "poor_fit" else "warning"
        return FitVerdict(
            status,
            ["too few stable particles to judge the training fit", *verdict.reasons],
            verdict.measures,
        )
    return verdict


# A generative fit whose noise scale swallows the data: its bands cover the recording only
# because it calls a structured misfit noise (a unit mistake the data checks cannot see, e.g. a
# force in kgf inside the prior box's range). poor_fit when the fitted sigma_x is this many
# times the recording's own white noise, this share of the displacement's range, and the
# standardised residuals this autocorrelated (lag 1), all three at once.
MISFIT_TO_NOISE, MISFIT_TO_RANGE, MISFIT_LAG1 = 10.0, 0.1, 0.9

# A warning when the fitted displacement noise is this many times the recording's own white
# noise (second differences, model.noise.estimate_displacement_noise). On 60 SBC data sets of
# the default command (experiments/results/sbc_default_s14*/, the estimate within 0.94-1.12 of
# the true noise) the ratio was 0.89-1.08 wherever the fit was right, and 2.1 and 3.4 in the two
# fits that had ended in a wrong basin (the truths 130 and 198 posterior sd away, "trusted"
# importance weights): the global search's failure shows as noise the recording does not have.
# On a real recording the same ratio also means model error (the model cannot follow the
# record to within its sensor noise): a warning, not a poor fit.
NOISE_ABOVE_RECORDING = 1.3


def _noise_above_recording(problem, posterior) -> tuple[str, dict] | None:
    """(reason, measures) when the fitted sigma_x is :data:`NOISE_ABOVE_RECORDING` times the
    recording's own white noise or more, else None."""
    from ..model.noise import estimate_displacement_noise

    labels = list(getattr(problem, "labels", ()))
    if "sigma_x" not in labels:
        return None
    th = np.asarray(posterior.theta, float)[:, labels.index("sigma_x")]
    th = th[np.isfinite(th)]
    try:
        own = float(estimate_displacement_noise(problem.obs).sigma)
    except ConfigError:
        return None
    if not len(th) or not own > 0:
        return None
    fitted = float(np.exp(np.median(th)))
    if fitted < NOISE_ABOVE_RECORDING * own:
        return None
    m = {"fitted_sigma_m": fitted, "own_noise_m": own, "ratio": fitted / own}
    return (
        f"the fit needs a displacement noise of {fitted:.3g} m, {fitted / own:.2g}x the "
        f"recording's own ({own:.3g} m, from its second differences): the model does not follow "
        "the recording to within its noise. Either the start pipeline ended in a wrong basin "
        "(simulated data: the truths were then far outside the intervals) or the model misses "
        "something the recording has; compare with the plots, try another --seed",
        m,
    )


def _misfit_called_noise(problem, posterior, measures: dict) -> tuple[str, dict] | None:
    """(reason, measures) when the fitted displacement noise is a structured misfit
    (:data:`MISFIT_TO_NOISE`), else None."""
    from ..model.noise import estimate_displacement_noise

    labels = list(getattr(problem, "labels", ()))
    lag1 = ((measures.get("ppc") or {}).get("lag1")) if isinstance(measures, dict) else None
    if "sigma_x" not in labels or lag1 is None or not lag1 >= MISFIT_LAG1:
        return None
    th = np.asarray(posterior.theta, float)[:, labels.index("sigma_x")]
    th = th[np.isfinite(th)]
    obs = problem.obs
    x = np.asarray(obs.displacement, float)[np.asarray(obs.mask, bool)]
    try:
        own = float(estimate_displacement_noise(obs).sigma)
    except ConfigError:
        return None
    if not len(th) or not len(x) or own <= 0:
        return None
    fitted, span = float(np.exp(np.median(th))), float(np.ptp(x))
    m = {"fitted_sigma_m": fitted, "own_noise_m": own, "range_m": span, "lag1": float(lag1)}
    if fitted < MISFIT_TO_NOISE * own or fitted < MISFIT_TO_RANGE * span:
        return None
    return (
        f"model misfit called noise: the fit needs a displacement noise of {fitted:.3g} m "
        f"({fitted / span:.0%} of the displacement's range) where the recording's own noise is "
        f"{own:.3g} m ({fitted / own:.3g}x), with residuals autocorrelated (lag-1 {lag1:.2f}): "
        "the model cannot reproduce the recording with any gains in the prior box; force or "
        "displacement in other units (kgf, lbf), or the wrong tree?",
        m,
    )


def _noise_covariance(problem, posterior, pred, generative: bool, noise_sigma):
    """``(white variance, extra [B, T, T] or None)`` of the run's noise model for
    :func:`treeinfer.evaluation.ppc.standardised_residuals`. Generative: sigma_x^2 of each draw
    (Student-t: times df / (df - 2)), plus the force-noise covariance (``--noise-force``) or the
    AR(1) one (``ar1``, at the posterior medians). Boltzmann: the data's own white-noise
    estimate (residual structure beyond the sensor noise is what it can check)."""
    settings = getattr(problem, "settings", None) or {}
    kind = settings.get("likelihood")
    obs = problem.obs
    if not generative:
        from ..model.noise import estimate_displacement_noise

        try:
            return estimate_displacement_noise(obs).sigma ** 2, None
        except ConfigError:
            return None, None
    labels = list(getattr(problem, "labels", ()))
    theta = np.asarray(posterior.theta, float)
    sigma = getattr(pred, "sigma", None)
    if sigma is None:
        sigma = noise_sigma
    if sigma is None:
        return None, None
    nvar = np.asarray(sigma, float) ** 2
    extra = None
    if kind == "student_t":
        df = float(settings.get("student_t_df") or 4.0)
        nvar = nvar * df / (df - 2.0)
    elif kind == "ar1" and {"sigma_x", "sigma_c", "rho"} <= set(labels):
        sx = np.exp(np.median(theta[:, labels.index("sigma_x")]))
        sc = np.exp(np.median(theta[:, labels.index("sigma_c")]))
        rho = 1.0 / (1.0 + np.exp(-np.median(theta[:, labels.index("rho")])))
        t = np.arange(np.shape(obs.displacement)[-1])
        ar = sc**2 * rho ** np.abs(t[:, None] - t[None, :])
        nvar, extra = sx**2, np.broadcast_to(ar, (np.shape(obs.displacement)[0], *ar.shape))
    fmodel = getattr(getattr(problem, "noise", None), "force_noise", None)
    if fmodel is not None:
        try:
            extra = fmodel.basis(problem.sim, np.asarray(obs.force), np.asarray(obs.mask, bool))
            extra = extra.covariance()
        except Exception:  # noqa: BLE001 -- the band's diagonal is a usable fallback
            fv = getattr(pred, "force_variance", None)
            extra = None if fv is None else np.stack([np.diag(v) for v in np.asarray(fv)])
    return nvar, extra
