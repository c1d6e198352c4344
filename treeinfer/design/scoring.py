"""Ranking candidate pulls (:func:`score_candidates`) and the ranked table
(:class:`Suggestions`, :func:`plot_scores`); the estimators are in
:mod:`treeinfer.design.estimators`, the overview in :mod:`treeinfer.design`."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError
from ..model.gradients import default_rel_step
from ..sim import Simulator
from .candidates import (
    STANDARD_TIMING,
    Candidate,
    Target,
    _check_candidate,
    candidate_forces,
    candidate_spec,
)
from .estimators import (
    _directions_array,
    _laplace_scores,
    _nmc_scores,
    particle_covariance,
)


# ==== the ranked table ============================================================================
class Suggestions(NamedTuple):
    """Candidates ranked by score (best first).

    candidates: the C candidates, best first. score: [C] nats (objective ``"eig"``), m^2 of
    predictive variance removed (``"target"``) or log units^2 of one parameter's variance
    removed (``"parameter"``). stable_share: [C] share of the subsampled particles whose
    rollouts of that candidate were all stable. band_std_before, band_std_after: [C] the
    target's linearised predictive std (m) or the parameter's std (log units) before/after
    (None for ``"eig"``). settings: estimator, sigma_x, particle counts, rel_step, duration, dt,
    cost in rollouts, target. specs: [C] the force-profile spec of each candidate.
    """

    candidates: tuple[Candidate, ...]
    score: np.ndarray
    stable_share: np.ndarray
    band_std_before: np.ndarray | None
    band_std_after: np.ndarray | None
    specs: tuple[str, ...]
    settings: dict

    @property
    def best(self) -> Candidate:
        return self.candidates[0]

    def to_dict(self) -> dict:
        """JSON-serialisable: settings and one row per candidate (rank order)."""
        rows = []
        for i, c in enumerate(self.candidates):
            row = {
                "rank": i + 1,
                **c.to_dict(),
                "spec": self.specs[i],
                "score": _num(self.score[i]),
                "stable_share": _num(self.stable_share[i]),
            }
            if self.band_std_after is not None:
                unit = "log" if self.settings.get("objective") == "parameter" else "m"
                row[f"std_before_{unit}"] = _num(self.band_std_before[i])
                row[f"std_after_{unit}"] = _num(self.band_std_after[i])
            rows.append(row)
        return {"settings": self.settings, "candidates": rows}

    def table(self, top: int | None = None) -> str:
        """Plain-text ranked table (the ``top`` best rows; all by default)."""
        obj = self.settings.get("objective", "eig")
        tgt = obj != "eig"
        unit, after, scale = {
            "eig": ("EIG [nats]", "", 1.0),
            "target": ("var cut [mm^2]", "band std [mm]", 1e3),
            "parameter": ("var cut [log^2]", "std after", 1.0),
        }[obj]
        head = f"{'rank':>4}  {'grasp':>6}  {'peak [N]':>8}  {'kind':>7}  {'direction':>18}"
        head += f"  {unit:>15}"
        head += f"  {after:>13}" if tgt else ""
        head += f"  {'stable':>6}"
        lines = [head]
        n = len(self.candidates) if top is None else min(top, len(self.candidates))
        for i in range(n):
            c = self.candidates[i]
            d = (
                "gravity"
                if c.direction is None
                else "(" + ",".join(f"{v:.2f}" for v in c.direction) + ")"
            )
            s = self.score[i] * scale**2
            line = (
                f"{i + 1:>4}  {c.grasp_fraction:>6.3g}  {c.peak_force:>8.3g}  {c.profile_kind:>7}"
            )
            line += f"  {d:>18}  {s:>15.4g}"
            if tgt:
                line += f"  {scale * self.band_std_after[i]:>13.3g}"
            lines.append(line + f"  {self.stable_share[i]:>6.0%}")
        return "\n".join(lines)


def _num(x):
    x = float(x)
    return x if math.isfinite(x) else None


def score_candidates(
    sim: Simulator,
    theta,
    candidates: Sequence[Candidate],
    sigma_x: float,
    duration: float,
    *,
    valid=None,
    n_particles: int = 32,
    target: Target | None = None,
    parameter: str | None = None,
    estimator: str = "laplace",
    rel_step: float | None = None,
    seed: int = 0,
) -> Suggestions:
    """Rank ``candidates`` for the posterior particles ``theta [P, 2R]`` (log Kp, log Kd).

    Args:
      sim: the compiled tree (its ``obs_dt`` is the candidates' sample interval).
      candidates: from :func:`candidate_grid`.
      sigma_x: m, std of the white Gaussian noise on each displacement sample.
      duration: s, length of each candidate pull (T = duration / obs_dt samples).
      valid: [P] bool, particles to use (default: all with finite theta).
      n_particles: M, size of the seeded subsample the sensitivities are taken at (all
        particles still give the covariance); nested MC uses all valid particles.
      target: score by the reduction of this manipulation's predictive variance instead of EIG.
      parameter: score by the expected reduction of one parameter's posterior variance (log
        units^2, linearised as for ``target``): a label such as ``"Kd[branch1]"``, or
        ``"worst"`` for the parameter with the largest particle std now. ``band_std_*`` then
        hold that parameter's std before/after. No extra rollouts.
      estimator: ``"laplace"`` (default) or ``"nmc"`` (nested Monte Carlo; EIG only).
      rel_step: central-difference step in log units (default ``eps ** (1/3)``).
      seed: seeds the subsample and the nested-MC noise.

    Returns :class:`Suggestions`, best first (ties and NaN scores last).
    """
    if not (isinstance(sigma_x, (int, float)) and math.isfinite(sigma_x) and sigma_x > 0):
        raise ConfigError(f"sigma_x: must be a positive number of metres, got {sigma_x!r}")
    if estimator not in ("laplace", "nmc"):
        raise ConfigError(f"estimator: expected 'laplace' or 'nmc', got {estimator!r}")
    if estimator == "nmc" and (target is not None or parameter is not None):
        raise ConfigError(
            "estimator 'nmc' scores the EIG only; use 'laplace' with a target or parameter"
        )
    if target is not None and parameter is not None:
        raise ConfigError("give a target or a parameter to score by, not both")
    if (
        isinstance(n_particles, bool)
        or not isinstance(n_particles, (int, np.integer))
        or n_particles < 2
    ):
        raise ConfigError(f"n_particles: must be an integer >= 2, got {n_particles!r}")
    if not candidates:
        raise ConfigError("candidates: none given")
    candidates = [_check_candidate(Candidate(*c)) for c in candidates]
    theta = np.asarray(theta, np.float32)
    if theta.ndim != 2 or theta.shape[1] != 2 * sim.n_joints:
        raise ConfigError(
            f"theta: expected [P, {2 * sim.n_joints}] (log Kp, log Kd), got {theta.shape}"
        )
    ok = np.all(np.isfinite(theta), axis=1)
    if valid is not None:
        ok &= np.asarray(valid, bool)
    pts = theta[ok]
    cov = particle_covariance(pts)
    labels = [f"Kp[{n}]" for n in sim.joint_names] + [f"Kd[{n}]" for n in sim.joint_names]
    onehot = None
    if parameter is not None:
        if parameter == "worst":
            parameter = labels[int(np.argmax(np.diag(cov)))]
        if parameter not in labels:
            raise ConfigError(f"parameter: expected 'worst' or one of {labels}, got {parameter!r}")
        onehot = jnp.asarray(np.eye(len(labels))[labels.index(parameter)], sim.dtype)
    forces = candidate_forces(candidates, duration, sim.obs_dt)
    grasp = np.asarray([c.grasp_fraction for c in candidates], np.float32)
    direction = _directions_array(candidates + ([target.candidate()] if target else []), sim)
    rng = np.random.default_rng(seed)
    dtype = sim.dtype
    c_dir = None if direction is None else jnp.asarray(direction[: len(candidates)], dtype)
    if estimator == "laplace":
        m = min(int(n_particles), len(pts))
        sub = pts[np.sort(rng.choice(len(pts), m, replace=False))]
        tgt = None
        if target is not None:
            tf = candidate_forces([target.candidate()], duration, sim.obs_dt)[0]
            td = jnp.zeros(3, dtype) if direction is None else jnp.asarray(direction[-1], dtype)
            tgt = (jnp.asarray(tf, dtype), jnp.asarray(target.grasp_fraction, dtype), td)
        h = default_rel_step(dtype) if rel_step is None else float(rel_step)
        out, share = _laplace_scores(
            sim,
            jnp.asarray(sub, dtype),
            jnp.asarray(cov, dtype),
            jnp.asarray(forces, dtype),
            jnp.asarray(grasp, dtype),
            c_dir,
            h,
            float(sigma_x),
            tgt,
            onehot,
        )
        out, share = np.asarray(out, float), np.asarray(share, float)
        d = pts.shape[1]
        cost = m * 2 * d * (len(candidates) + (1 if target else 0))
        if target is None and onehot is None:
            score, before, after = out, None, None
        else:
            before, after = out
            score = before - after
            before, after = np.sqrt(np.clip(before, 0, None)), np.sqrt(np.clip(after, 0, None))
    else:
        m, h = len(pts), None
        key = jax.random.key(int(seed))
        score, share = _nmc_scores(
            sim,
            jnp.asarray(pts, dtype),
            jnp.asarray(forces, dtype),
            jnp.asarray(grasp, dtype),
            c_dir,
            float(sigma_x),
            key,
        )
        score, share = np.asarray(score, float), np.asarray(share, float)
        before = after = None
        cost = m * len(candidates)
    order = np.argsort(np.where(np.isfinite(score), -score, np.inf), kind="stable")
    objective = "eig" if target is None else "target"
    objective = "parameter" if parameter is not None else objective
    settings = {
        "objective": objective,
        "estimator": estimator,
        "score_units": {
            "eig": "nats",
            "target": "m^2 (mean predictive variance removed)",
            "parameter": "log units^2 (posterior variance removed)",
        }[objective],
        "parameter": parameter,
        "sigma_x_m": float(sigma_x),
        "n_posterior_particles": len(pts),
        "n_particles_used": int(m),
        "rel_step": h,
        "duration_s": float(duration),
        "dt_s": float(sim.obs_dt),
        "n_candidates": len(candidates),
        "cost_rollouts": int(cost),
        "seed": int(seed),
        "target": None
        if target is None
        else {
            **target.candidate().to_dict(),
            "description": target.describe(),
            "spec": candidate_spec(target.candidate(), duration),
        },
        "standard_timing": STANDARD_TIMING,
    }
    specs = [candidate_spec(c, duration) for c in candidates]
    pick = lambda a: None if a is None else np.asarray(a)[order]
    return Suggestions(
        candidates=tuple(candidates[i] for i in order),
        score=np.asarray(score)[order],
        stable_share=np.asarray(share)[order],
        band_std_before=pick(before),
        band_std_after=pick(after),
        specs=tuple(specs[i] for i in order),
        settings=settings,
    )


# ==== plot ========================================================================================
def plot_scores(suggestions: Suggestions):
    """Score over grasp fraction, one line per peak force, one panel per (kind, direction).

    Returns ``(fig, axes)``."""
    import matplotlib.pyplot as plt

    cands = suggestions.candidates
    groups = sorted({(c.profile_kind, c.direction) for c in cands}, key=str)
    fig, axes = plt.subplots(1, len(groups), figsize=(4.2 * len(groups), 3.4), squeeze=False)
    axes = axes[0]
    scale, ylabel = {
        "eig": (1.0, "expected information gain [nats]"),
        "target": (1e6, "predictive variance removed [mm$^2$]"),
        "parameter": (
            1.0,
            f"variance of {suggestions.settings.get('parameter')} removed [log$^2$]",
        ),
    }[suggestions.settings.get("objective", "eig")]
    forces = sorted({c.peak_force for c in cands})
    cmap = plt.get_cmap("viridis")
    for ax, (kind, direction) in zip(axes, groups):
        for j, f in enumerate(forces):
            rows = [
                (c.grasp_fraction, s)
                for c, s in zip(cands, suggestions.score)
                if c.profile_kind == kind and c.direction == direction and c.peak_force == f
            ]
            if not rows:
                continue
            rows.sort()
            g, s = np.asarray(rows, float).T
            ax.plot(
                g, s * scale, "o-", ms=3, color=cmap(j / max(1, len(forces) - 1)), label=f"{f:g} N"
            )
        b = suggestions.best
        if b.profile_kind == kind and b.direction == direction:
            ax.plot([b.grasp_fraction], [suggestions.score[0] * scale], "r*", ms=12, label="best")
        d = "gravity" if direction is None else str(list(direction))
        ax.set_title(f"{kind} pull, {d}")
        ax.set_xlabel("grasp fraction")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[-1].legend(fontsize=7, title="peak force", title_fontsize=7)
    fig.tight_layout()
    return fig, axes
