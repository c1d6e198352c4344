"""Posterior predictive bands of a :class:`treeinfer.inference.posterior.Posterior` under a force
profile, with the checks that keep a prediction inside what the run supports."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import PosteriorError

# A peak force beyond this multiple of the training data's largest is an extrapolation the data
# never probed (larger bends, other contacts); predict(extrapolate=True) allows it knowingly.
FORCE_MARGIN = 1.5


@dataclass(frozen=True, eq=False)
class PredictiveBand:
    """The posterior predictive band of the grasp point's displacement (m).

    time: [T] s. force: [T] or [B, T] N (the shape given). mean, lower, upper: the same shape
    as ``force``: the predictive mean and the central ``level`` band (simulation + the run's
    fitted noise model; the parameter band when the run knows no noise level, ``kind`` says
    which). draws: [S, ...] the simulation of every usable particle. parameter_lower/upper: the
    band of the simulations alone. grasp_fraction: where the force acted."""

    time: np.ndarray
    force: np.ndarray
    mean: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    draws: np.ndarray
    parameter_lower: np.ndarray
    parameter_upper: np.ndarray
    level: float
    kind: str
    grasp_fraction: float
    n_excluded: int = 0

    def plot(self, recording=None, *, truth=None, title=None, max_draws: int = 20):
        """The band (grey), mean (dashed) and draws (thin); ``recording`` ([T] or [B, T] m, a
        real pull's measured displacement) or ``truth`` (a simulation's noise-free response)
        in red under that name. Returns ``(fig, axes)``."""
        from .plots import plot_band_grid, plot_trajectory_bands

        if recording is not None and truth is not None:
            raise PosteriorError("plot: give a recording or a truth, not both")
        ref, ref_label = (recording, "recording") if truth is None else (truth, "truth")
        label = f"{self.level:.0%} {self.kind}"
        if self.mean.ndim == 1:
            return plot_trajectory_bands(
                self.time,
                self.lower,
                self.upper,
                self.mean,
                ref,
                self.draws,
                title=title or f"{label}, grasp at {self.grasp_fraction:g} of the branch",
                band_label=f"{self.level:.0%} band",
                reference_label=ref_label,
                max_samples=max_draws,
            )
        return plot_band_grid(
            self.time,
            self.lower,
            self.upper,
            self.mean,
            ref,
            np.swapaxes(self.draws, 0, 1),
            titles=[f"force profile {b}" for b in range(self.mean.shape[0])],
            suptitle=title or label,
            reference_label=ref_label,
            max_samples=max_draws,
        )


def _grasp(post, grasp) -> float:
    ctx = post.context
    tree = ctx.tree
    branch = None
    if isinstance(grasp, (tuple, list)):
        if len(grasp) != 2:
            raise PosteriorError(f"grasp: expected a fraction or (branch, fraction), got {grasp!r}")
        branch, grasp = grasp
    if branch is not None and tree is not None and branch != tree.grasp_branch:
        known = ", ".join(tree.names)
        raise PosteriorError(
            f"grasp: branch {branch!r} is not where this run's tree is grasped "
            f"({tree.grasp_branch!r}); its simulator pulls that branch only"
            + ("" if branch in tree.names else f" (and the tree has no branch {branch!r}: {known})")
        )
    if grasp is None:
        g = (ctx.problem_settings or {}).get("grasp_fraction")
        if isinstance(g, (list, tuple)):  # per-recording pulls: the first one's
            g = g[0]
        grasp = g if g is not None else (tree.grasp_fraction if tree is not None else None)
        if grasp is None:
            raise PosteriorError("grasp: unknown for this posterior; give a fraction in (0, 1]")
    if isinstance(grasp, bool) or not isinstance(grasp, (int, float, np.floating)):
        raise PosteriorError(f"grasp: expected a fraction in (0, 1], got {grasp!r}")
    g = float(grasp)
    if not (np.isfinite(g) and 0 < g <= 1):
        name = tree.grasp_branch if tree is not None else "the grasped branch"
        raise PosteriorError(
            f"grasp: {g!r} is outside branch {name!r}: the force acts at a fraction in (0, 1] "
            "of the branch's length from its joint"
        )
    return g


def _forces(post, forces, extrapolate: bool) -> np.ndarray:
    try:
        f = np.asarray(forces, float)
    except (TypeError, ValueError):
        raise PosteriorError("forces: expected numbers, N ([T] or [B, T])") from None
    if f.ndim not in (1, 2) or f.shape[-1] < 2:
        raise PosteriorError(f"forces: expected [T] or [B, T] N with T >= 2, got shape {f.shape}")
    bad = np.flatnonzero(~np.isfinite(f.reshape(-1)))
    if bad.size:
        raise PosteriorError(
            f"forces: {bad.size} value(s) not finite (first at flat index {bad[0]})"
        )
    ref = post.context.force_max
    peak = float(np.max(np.abs(f)))
    if ref is not None and peak > FORCE_MARGIN * ref and not extrapolate:
        raise PosteriorError(
            f"forces: peak {peak:.4g} N is more than {FORCE_MARGIN:g} x the largest force of the "
            f"training data ({ref:.4g} N); the posterior has not seen such loads. Pass "
            "extrapolate=True to predict anyway"
        )
    return f


def predict_band(post, forces, grasp=None, *, level: float, extrapolate: bool) -> PredictiveBand:
    """:meth:`treeinfer.inference.posterior.Posterior.predict`."""
    from .bands import _check_level
    from .predictive import noise_for, predict_run

    _check_level(level)
    ctx = post.context
    if ctx is None or ctx.sim is None:
        raise PosteriorError(
            "predict: this posterior carries no simulator (made without a problem); use "
            "treeinfer.infer's result or treeinfer.load_posterior(run_folder)"
        )
    rows_ok = post.usable
    post._rows()  # the fit verdict and usable-particle checks
    g = _grasp(post, grasp)
    f = _forces(post, forces, extrapolate)
    f2 = np.atleast_2d(f)
    settings = ctx.problem_settings or {}
    sigma, kind = noise_for(post.theta, ctx.sim.n_joints, settings)
    pred = predict_run(
        ctx.sim,
        post.theta,
        f2,
        g,
        rows_ok,
        level=level,
        noise_sigma=sigma,
        noise_kind=kind,
        model=ctx.model,  # the forces are taken as applied: no force-noise term (CLI predict
    )  # adds one for a recording's measured force)
    lower, upper = pred.band()
    band_kind = (
        "parameter band (no noise model known)"
        if pred.predictive_lower is None
        else "predictive band (simulation + fitted noise)"
    )
    one = f.ndim == 1

    def shaped(a):
        a = np.asarray(a)
        return a[0] if one else a

    draws = np.asarray(pred.tau)[np.asarray(pred.valid, bool)]
    return PredictiveBand(
        time=np.arange(f.shape[-1]) * float(ctx.sim.obs_dt),
        force=f,
        mean=shaped(pred.mean),
        lower=shaped(lower),
        upper=shaped(upper),
        draws=draws[:, 0] if one else draws,
        parameter_lower=shaped(pred.lower),
        parameter_upper=shaped(pred.upper),
        level=float(level),
        kind=band_kind,
        grasp_fraction=g,
        n_excluded=int((~np.asarray(pred.valid, bool)).sum()),
    )
