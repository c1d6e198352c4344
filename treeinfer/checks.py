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

After inference, :func:`fit_checks` judges the training fit: residuals far beyond the noise
scale (fitted, or implied by kT through :func:`noise_from_kT`), the share of training points
outside the predictive band, posterior mass at a prior-box edge, and a posterior no narrower
than the prior (the data had no effect). It returns a :class:`FitVerdict` with ``status`` one
of ``ok | warning | poor_fit`` and the reasons. The command line ends a ``poor_fit`` run with
exit code 4 (:data:`POOR_FIT_EXIT_CODE`) unless ``--allow-poor-fit``.

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
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from .checks_data import (  # noqa: F401 -- re-exported: the old import path keeps working
    data_checks,
)
from .checks_tree import (  # noqa: F401 -- re-exported: the old import path keeps working
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
    simulation_cost_check,
    static_compliance,
)
from .tree import Tree

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
    """Displacement noise sigma (m) for which :func:`treeinfer.likelihood.suggest_kT` gives
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


RESIDUAL_WARN, RESIDUAL_POOR = 3.0, 10.0  # RMS residual / noise sigma
OUTSIDE_WARN, OUTSIDE_POOR = 3.0, 0.5  # x (1 - level); absolute fraction
EDGE_BAND = 0.05  # share of the log box width counted as "at the edge"
EDGE_SHARE = 0.5  # share of particles at/beyond one edge that is flagged
NO_EFFECT = 0.9  # posterior std / prior std (log space) above which the data had no effect


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
) -> FitVerdict:
    """Judge a finished run's training fit.

    Args:
      residuals: [B, T] m, predictive mean minus observed displacement (or None).
      mask: [B, T] bool, real samples. noise_sigma: m, the fitted displacement noise, or
        :func:`noise_from_kT` of the run's kT.
      fraction_outside: share (0-1) of training points outside the ``level`` predictive band.
      theta: [P, D] final particles in log space; lower, upper: [D] log prior box;
        labels: D names; valid: [P] bool, particles to use.

    Returns:
      :class:`FitVerdict`.
    """
    poor: list[str] = []
    warn: list[str] = []
    m: dict = {}
    if residuals is not None and noise_sigma is not None and noise_sigma > 0:
        r = np.asarray(residuals, float)
        mk = np.ones(r.shape, bool) if mask is None else np.asarray(mask, bool)
        ok = mk & np.isfinite(r)
        if ok.any():
            rms = float(np.sqrt(np.mean(r[ok] ** 2)))
            ratio = rms / float(noise_sigma)
            m["residual_rms_m"], m["noise_sigma_m"], m["residual_to_noise"] = (
                rms,
                float(noise_sigma),
                ratio,
            )
            msg = (
                f"training residuals (RMS {rms:.3g} m) are {ratio:.3g}x the noise scale "
                f"({noise_sigma:.3g} m): the model does not explain the data"
            )
            if ratio > RESIDUAL_POOR:
                poor.append(msg)
            elif ratio > RESIDUAL_WARN:
                warn.append(msg)
    if fraction_outside is not None and math.isfinite(fraction_outside):
        expected = 1.0 - level
        m["fraction_outside"] = float(fraction_outside)
        msg = (
            f"{fraction_outside:.1%} of training points lie outside the {level:.0%} "
            "predictive band "
            f"(about {expected:.0%} expected)"
        )
        if fraction_outside > OUTSIDE_POOR:
            poor.append(msg)
        elif fraction_outside > OUTSIDE_WARN * expected:
            warn.append(msg)
    if theta is not None and lower is not None and upper is not None:
        th = np.asarray(theta, float)
        lo, hi = np.asarray(lower, float), np.asarray(upper, float)
        ok = np.all(np.isfinite(th), axis=1)
        if valid is not None:
            ok &= np.asarray(valid, bool)
        th = th[ok]
        labels = list(labels) if labels is not None else [f"theta[{j}]" for j in range(th.shape[1])]
        if len(th) >= 2:
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
                        (poor if beyond else warn).append(msg)
            m["at_prior_edge"] = edge
            flat = [lab for lab, r in zip(labels, ratio) if r > NO_EFFECT]
            if flat and len(flat) == len(labels):
                poor.append(
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
    """:func:`fit_checks` on what :func:`treeinfer.runs.run_inference` has at hand.

    Args:
      problem: the inference problem (``obs`` [B, T] training data, ``lower``/``upper`` log
        prior box [D], ``labels``). posterior: ``theta`` [P, D] log gains.
      fit: the run's training fit: ``stable`` [P], ``prediction`` (``mean`` [B, T] m; None if
        too few particles were stable), ``metrics`` (``fraction_outside``).
      noise_sigma: the fitted displacement noise (m) if the noise model has one; None: the
        residual test is skipped (kT is a temperature the user chose, not a measured noise, so
        the sigma it implies is no yardstick for residuals).
    """
    pred = fit.get("prediction")
    metrics = fit.get("metrics") or {}
    residuals = mask = None
    if pred is not None:
        residuals = np.asarray(pred.mean, float) - np.asarray(problem.obs.displacement, float)
        mask = np.asarray(problem.obs.mask, bool)
    frac = metrics.get("fraction_outside")
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
    )
    if pred is None:  # the unstable-share limit already judged this; do not fail twice
        status = verdict.status if verdict.status == "poor_fit" else "warning"
        return FitVerdict(
            status,
            ["too few stable particles to judge the training fit", *verdict.reasons],
            verdict.measures,
        )
    return verdict
