"""Simulation-based calibration (SBC, Talts et al. 2018) of treeinfer's posteriors.

SBC checks the whole inference pipeline against its own generative model: draw parameters
``theta* ~ prior``, simulate a data set ``y ~ p(y | theta*)``, run inference on ``y`` and record
the rank of ``theta*_d`` among ``L`` posterior draws, for every parameter ``d``. If the draws come
from the exact posterior, every rank is uniform on ``{0, ..., L}`` (over prior draws); a
U-shaped histogram means over-confident posteriors, a hump under-confident ones, a slope bias.

What is here:

* statistics (sampler-agnostic, numpy/scipy): :func:`sbc_ranks`, :func:`fractional_ranks`,
  :func:`rank_coverage` (coverage of central intervals at several levels), :func:`rank_uniformity`
  (chi-square on equal bins of the fractional rank and Kolmogorov-Smirnov, p-values, a pass/fail
  at 1% with a Bonferroni correction over parameters), :func:`binomial_band`,
  :func:`summarize_sbc`, and the plots :func:`plot_rank_histograms`, :func:`plot_coverage`;
* the prior: :func:`sample_smoothed_box` (exact draws from treeinfer's smoothed box prior) and the
  noise prior ``log sigma_x ~ Normal(log centre, scale)`` (:func:`treeinfer.noise.log_sigma_prior`);
* :func:`run_tree_sbc`: the batched tree study. One jitted program ``vmap``s the sampler's whole
  ``lax.scan`` over many data sets; the log-density takes the observations (and the force
  profiles) as arguments, the simulator is a black box with central-difference derivatives
  (:func:`treeinfer.gradients.finite_difference_jvp`, valid under ``vmap``). Data sets are
  processed in chunks of ``chunk`` (a GPU takes hundreds at once; the CPU a few).

Coverage from ranks: with the fractional rank ``u = (rank + V) / (L + 1)``, ``V ~ U(0, 1)``
(exactly uniform on (0, 1) under calibration, ties included), the truth lies inside the central
``a`` interval of the posterior draws iff ``|u - 1/2| <= a / 2``. So the expected coverage is
exactly ``a`` for a calibrated posterior with any L, without quantile interpolation.

Sampler (``sampler="mh"``, the default, and why): SBC needs (nearly) exact, independent
posterior draws per data set. The posterior of 5 noisy pulls is ~1% wide in log gain inside a
prior box ~5 log units wide, so neither random-walk MH from the box nor SVGD with a fixed Adam
step gets there in a few hundred iterations (measured: 24 data sets, SVGD 150 iterations then MH,
posterior stds as wide as the prior, sigma_x ranks all 0: FAIL). So, per data set:

1. Adam ascent of P starts drawn in the prior box (learning rate decaying 100x over
   ``iterations``; gradients of the simulator by central differences), the best end point is
   the posterior mode;
2. P random-walk Metropolis chains start at the mode (+1e-3 jitter). Warm-up in 4 phases: the
   proposal is ``exp(log_s) chol(C)`` with C the chains' ensemble covariance re-estimated at
   each phase start (first phase 0.01 I) and ``log_s`` tuned to ~25% acceptance; then
   ``mh_steps`` steps with the proposal fixed (exact MH, the adaptation stops); the final state
   of every chain is one draw (L = P, warm-up discarded, one state per chain).

The exact accept/reject makes the draws asymptotically exact whatever stage 1 did; SBC then tests
whether the chains mixed. Limitation: a posterior with several separated modes is sampled only
around the best one. ``sampler="svgd"`` uses P final SVGD particles (Adam, RBF median heuristic,
box prior only) as draws: SBC then measures SVGD's own calibration. NNSVGD is not offered: its
target adds the learned inequality prior, which the truths would have to be drawn from as well.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.stats

from .errors import ConfigError

__all__ = [
    "COVERAGE_LEVELS",
    "SBC_SAMPLERS",
    "SBCConfig",
    "SBCResult",
    "binomial_band",
    "fractional_ranks",
    "plot_coverage",
    "plot_rank_histograms",
    "rank_coverage",
    "rank_uniformity",
    "run_tree_sbc",
    "sample_smoothed_box",
    "sbc_ranks",
    "summarize_sbc",
]

COVERAGE_LEVELS = (0.5, 0.8, 0.9, 0.95)
SBC_SAMPLERS = ("mh", "svgd")
_WARMUP_PHASES = 4  # MH warm-up phases (proposal covariance re-estimated at each start)
SBC_LIKELIHOODS = ("gaussian", "student_t")
ALPHA = 0.01  # family-wise level of the uniformity test (Bonferroni over parameters)


# =========================================================================== statistics


def sbc_ranks(truth, draws, rng: np.random.Generator | None = None) -> np.ndarray:
    """Rank of every true parameter among its posterior draws.

    Args:
      truth: ``[N, D]`` true parameters of N data sets (any units, same as ``draws``).
      draws: ``[N, L, D]`` L posterior draws per data set.
      rng: breaks ties (a draw equal to the truth) uniformly at random; None: seed 0.

    Returns ``[N, D]`` integers in ``0..L``: ``#{draws < truth} + Uniform{0..#{draws == truth}}``.
    """
    truth = np.asarray(truth, float)
    draws = np.asarray(draws, float)
    if (
        truth.ndim != 2
        or draws.ndim != 3
        or draws.shape[0] != truth.shape[0]
        or (draws.shape[2] != truth.shape[1])
    ):
        raise ConfigError(
            f"sbc_ranks: expected truth [N, D] and draws [N, L, D], got {truth.shape}, "
            f"{draws.shape}"
        )
    if not (np.all(np.isfinite(truth)) and np.all(np.isfinite(draws))):
        raise ConfigError("sbc_ranks: truth and draws must be finite")
    rng = np.random.default_rng(0) if rng is None else rng
    less = np.sum(draws < truth[:, None, :], axis=1)
    ties = np.sum(draws == truth[:, None, :], axis=1)
    return less + rng.integers(0, ties + 1)


def fractional_ranks(ranks, n_draws: int, rng: np.random.Generator | None = None) -> np.ndarray:
    """``u = (rank + V) / (L + 1)``, ``V ~ U(0, 1)``: exactly Uniform(0, 1) under calibration
    (a discrete uniform rank on 0..L spread over its cell). ``ranks [N, D]`` -> ``[N, D]``."""
    ranks = np.asarray(ranks)
    if np.any(ranks < 0) or np.any(ranks > n_draws):
        raise ConfigError(f"ranks: must lie in 0..{n_draws}")
    rng = np.random.default_rng(1) if rng is None else rng
    return (ranks + rng.uniform(size=ranks.shape)) / (n_draws + 1)


def rank_coverage(u, levels: Sequence[float] = COVERAGE_LEVELS) -> np.ndarray:
    """Observed coverage of central posterior intervals: ``[K, D]``, the share of data sets whose
    fractional rank ``u [N, D]`` lies within ``level / 2`` of 1/2 (truth inside the central
    ``level`` interval of the draws). Expected value: ``level`` exactly when calibrated."""
    u = np.asarray(u, float)
    return np.stack([np.mean(np.abs(u - 0.5) <= a / 2.0, axis=0) for a in levels])


def binomial_band(n: int, p: float, level: float = 0.99) -> tuple[float, float]:
    """Central ``level`` interval of a Binomial(n, p) count (scipy): the band a histogram bin
    with expected share ``p`` (or a coverage count) stays in with probability ~``level``."""
    lo = scipy.stats.binom.ppf((1 - level) / 2, n, p)
    hi = scipy.stats.binom.ppf(1 - (1 - level) / 2, n, p)
    return float(lo), float(hi)


def default_bins(n_datasets: int, n_draws: int) -> int:
    """Histogram bins: at least ~5 expected per bin (chi-square validity), at most 20 and at
    most L + 1."""
    return int(max(2, min(20, n_draws + 1, n_datasets // 5)))


def rank_uniformity(u, labels: Sequence[str], n_bins: int, alpha: float = ALPHA) -> dict:
    """Uniformity tests of the fractional ranks of each parameter.

    Tests (both exact under calibration, since ``u`` is continuous uniform): Pearson chi-square
    on ``n_bins`` equal bins (``scipy.stats.chisquare``, n_bins - 1 dof) and Kolmogorov-Smirnov
    against Uniform(0, 1) (``scipy.stats.kstest``). A parameter passes when both p-values exceed
    ``alpha / (2 D)`` (Bonferroni over D parameters and the two tests); the study passes at the
    family-wise level ``alpha`` when every parameter does.

    Returns ``{"alpha", "per_parameter_threshold", "n_bins", "parameters": {label: {...}},
    "pass"}``.
    """
    u = np.asarray(u, float)
    n, d = u.shape
    thr = alpha / (2 * d)
    out = {}
    for j, lab in enumerate(labels):
        counts = np.histogram(u[:, j], bins=n_bins, range=(0.0, 1.0))[0]
        chi = scipy.stats.chisquare(counts)
        ks = scipy.stats.kstest(u[:, j], "uniform")
        ok = bool(chi.pvalue > thr and ks.pvalue > thr)
        out[lab] = {
            "chi2": float(chi.statistic),
            "p_chi2": float(chi.pvalue),
            "ks": float(ks.statistic),
            "p_ks": float(ks.pvalue),
            "counts": counts.tolist(),
            "pass": ok,
        }
    return {
        "alpha": alpha,
        "per_parameter_threshold": thr,
        "correction": "Bonferroni over parameters and the two tests (chi-square, KS)",
        "n_bins": int(n_bins),
        "n_datasets": int(n),
        "parameters": out,
        "pass": all(v["pass"] for v in out.values()),
    }


@dataclass
class SBCResult:
    """Outcome of an SBC study.

    truth: ``[N, D]`` true parameters (theta units: log gains, log sigma_x).
    draws: ``[N, L, D]`` posterior draws (same units). ranks: ``[N, D]`` in 0..L.
    u: ``[N, D]`` fractional ranks. labels: D column names.
    coverage: ``[K, D]`` observed coverage at ``levels``. uniformity: :func:`rank_uniformity`.
    info: sampler diagnostics and timings (JSON-ready).
    """

    truth: np.ndarray
    draws: np.ndarray
    ranks: np.ndarray
    u: np.ndarray
    labels: tuple[str, ...]
    levels: tuple[float, ...]
    coverage: np.ndarray
    uniformity: dict
    info: dict = field(default_factory=dict)

    @property
    def n_draws(self) -> int:
        return int(self.draws.shape[1])


def summarize_sbc(
    truth,
    draws,
    labels: Sequence[str],
    levels: Sequence[float] = COVERAGE_LEVELS,
    n_bins: int | None = None,
    alpha: float = ALPHA,
    seed: int = 0,
    info: dict | None = None,
) -> SBCResult:
    """Ranks, fractional ranks, coverage and uniformity tests of ``draws [N, L, D]`` against
    ``truth [N, D]`` (ties and the fractional spread use ``seed``)."""
    labels = tuple(labels)
    truth = np.asarray(truth, float)
    draws = np.asarray(draws, float)
    if len(labels) != truth.shape[-1]:
        raise ConfigError(f"labels: expected {truth.shape[-1]} names, got {len(labels)}")
    for a in levels:
        if not 0.0 < a < 1.0:
            raise ConfigError(f"coverage levels: must lie in (0, 1), got {a}")
    rng = np.random.default_rng(seed)
    ranks = sbc_ranks(truth, draws, rng)
    u = fractional_ranks(ranks, draws.shape[1], rng)
    n_bins = default_bins(truth.shape[0], draws.shape[1]) if n_bins is None else int(n_bins)
    return SBCResult(
        truth,
        draws,
        ranks,
        u,
        labels,
        tuple(float(a) for a in levels),
        rank_coverage(u, levels),
        rank_uniformity(u, labels, n_bins, alpha),
        dict(info or {}),
    )


def coverage_table(result: SBCResult, band_level: float = 0.99) -> list[dict]:
    """One row per (level, parameter): expected, observed and the binomial band of the
    observed share for N data sets."""
    n = result.truth.shape[0]
    rows = []
    for k, a in enumerate(result.levels):
        lo, hi = binomial_band(n, a, band_level)
        for j, lab in enumerate(result.labels):
            rows.append(
                {
                    "level": a,
                    "parameter": lab,
                    "observed": float(result.coverage[k, j]),
                    "band_lower": lo / n,
                    "band_upper": hi / n,
                    "inside_band": bool(lo / n <= result.coverage[k, j] <= hi / n),
                }
            )
    return rows


def result_json(result: SBCResult, config: dict | None = None) -> dict:
    """JSON-ready summary: config, per-parameter p-values and pass, coverage table, info."""
    return {
        "method": "simulation-based calibration (Talts et al. 2018)",
        "config": config or {},
        "n_datasets": int(result.truth.shape[0]),
        "n_draws": result.n_draws,
        "labels": list(result.labels),
        "uniformity": result.uniformity,
        "coverage": coverage_table(result),
        "coverage_definition": "truth inside the central interval of the posterior draws, from "
        "fractional ranks u = (rank + V) / (L + 1): |u - 0.5| <= level / 2",
        "info": result.info,
    }


# =========================================================================== plots


def plot_rank_histograms(result: SBCResult, path=None, band_level: float = 0.99):
    """Rank histograms (one panel per parameter) with the ``band_level`` binomial band of a
    uniform histogram shaded; p-values in the titles. Returns the figure (saved to ``path``)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    d = len(result.labels)
    n = result.truth.shape[0]
    nb = result.uniformity["n_bins"]
    lo, hi = binomial_band(n, 1.0 / nb, band_level)
    ncol = min(d, 3)
    nrow = math.ceil(d / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.6 * ncol, 2.8 * nrow), squeeze=False)
    for j, lab in enumerate(result.labels):
        ax = axes[j // ncol][j % ncol]
        t = result.uniformity["parameters"][lab]
        ax.axhspan(lo, hi, color="0.85", label=f"{band_level:.0%} band (uniform)")
        ax.axhline(n / nb, color="0.5", lw=0.8)
        ax.bar(
            (np.arange(nb) + 0.5) / nb, t["counts"], width=1.0 / nb, color="C0", edgecolor="white"
        )
        ax.set_xlim(0, 1)
        ax.set_title(f"{lab}\np(chi2) {t['p_chi2']:.3g}, p(KS) {t['p_ks']:.3g}", fontsize=8)
        ax.set_xlabel(f"fractional rank (L = {result.n_draws})", fontsize=8)
        ax.set_ylabel("data sets", fontsize=8)
    for j in range(d, nrow * ncol):
        axes[j // ncol][j % ncol].axis("off")
    axes[0][0].legend(fontsize=7, loc="lower left")
    verdict = "PASS" if result.uniformity["pass"] else "FAIL"
    fig.suptitle(
        f"SBC rank histograms, N = {n}: {verdict} at {result.uniformity['alpha']:g} (Bonferroni)",
        fontsize=9,
    )
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=120)
        plt.close(fig)
    return fig


def plot_coverage(result: SBCResult, path=None, band_level: float = 0.99):
    """Expected vs observed coverage of central intervals, one line per parameter, with the
    ``band_level`` binomial band of a calibrated posterior. Returns the figure."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    n = result.truth.shape[0]
    grid = np.linspace(0.01, 0.99, 99)
    lo = np.array([binomial_band(n, a, band_level)[0] for a in grid]) / n
    hi = np.array([binomial_band(n, a, band_level)[1] for a in grid]) / n
    fig, ax = plt.subplots(figsize=(4.2, 4.0))
    ax.fill_between(grid, lo, hi, color="0.85", label=f"{band_level:.0%} band (calibrated)")
    ax.plot([0, 1], [0, 1], color="0.4", lw=0.8)
    levels = np.asarray(result.levels)
    for j, lab in enumerate(result.labels):
        ax.plot(levels, result.coverage[:, j], "o-", ms=3, lw=1, label=lab)
    ax.set_xlabel("expected coverage (central interval level)")
    ax.set_ylabel("observed coverage")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.legend(fontsize=7)
    ax.set_title(f"SBC coverage, N = {n} data sets, L = {result.n_draws} draws", fontsize=9)
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=120)
        plt.close(fig)
    return fig


def write_outputs(result: SBCResult, directory, config: dict | None = None) -> dict:
    """``sbc_summary.json``, ``ranks.csv``, ``draws.npz`` and ``plots/{rank_histograms,
    coverage}.png`` into ``directory`` (atomic writes). Returns the summary dict."""
    from pathlib import Path

    from ._io import atomic_save, atomic_write_json, atomic_write_text

    directory = Path(directory)
    (directory / "plots").mkdir(parents=True, exist_ok=True)
    summary = result_json(result, config)
    atomic_write_json(directory / "sbc_summary.json", summary)
    lines = ["dataset," + ",".join(f"rank_{lab},truth_{lab}" for lab in result.labels)]
    for i in range(result.truth.shape[0]):
        cells = [str(i)]
        for j in range(len(result.labels)):
            cells += [str(int(result.ranks[i, j])), repr(float(result.truth[i, j]))]
        lines.append(",".join(cells))
    atomic_write_text(directory / "ranks.csv", "\n".join(lines) + "\n")
    with atomic_save(directory / "draws.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(
                fh,
                truth=result.truth,
                draws=result.draws,
                ranks=result.ranks,
                labels=np.asarray(result.labels),
            )
    plot_rank_histograms(result, directory / "plots" / "rank_histograms.png")
    plot_coverage(result, directory / "plots" / "coverage.png")
    return summary


# =========================================================================== prior draws


def sample_smoothed_box(rng: np.random.Generator, lower, upper, sigma, n: int) -> np.ndarray:
    """``[n, D]`` exact draws from :func:`treeinfer.priors.smoothed_box` (normalised).

    Per coordinate the density is flat on ``[lower, upper]`` with half-normal tails of std
    ``sigma`` outside, i.e. the mixture: box with probability ``w / (w + sqrt(2 pi) sigma)``
    (``w = upper - lower``), otherwise a half-normal beyond either edge with equal chance.
    (Written here because no library ships this mixture; the test checks it against the
    density by a KS test on its CDF.)"""
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    s = np.broadcast_to(np.asarray(sigma, float), lo.shape)
    w = hi - lo
    p_box = w / (w + math.sqrt(2 * math.pi) * s)
    d = lo.size
    in_box = rng.uniform(size=(n, d)) < p_box
    upper_tail = rng.uniform(size=(n, d)) < 0.5
    h = np.abs(rng.normal(size=(n, d))) * s
    tail = np.where(upper_tail, hi + h, lo - h)
    return np.where(in_box, lo + rng.uniform(size=(n, d)) * w, tail)


# =========================================================================== tree SBC


@dataclass
class SBCConfig:
    """Everything one tree SBC study depends on (recorded in ``config.json``).

    likelihood: ``gaussian`` or ``student_t`` (data simulated AND inferred with it).
    noise_displacement: m, fixed sigma_x (given to inference); None: sigma_x inferred with prior
      ``log sigma_x ~ Normal(log noise_prior_center, sigma_prior_scale)`` and truths drawn from it.
    n_traj, duration, dt: pulls per data set (force profiles ``forces.profile_set("mixed")``,
      drawn afresh per data set), s, s.
    sampler: ``mh`` or ``svgd`` (module docstring). particles: P = L draws per data set.
    iterations: Adam ascent (mh) or SVGD (svgd) iterations; mh_warmup, mh_steps: MH warm-up
      and sampling steps per chain (mh).
    chunk: data sets per jitted program call.
    noise_force: relative force noise (share of the data set's peak |force|) on the RECORDED
      forces that drive inference (training and test). Not in the inference model (the noise
      engineer's decision: absorbed by sigma_x), so SBC is exact only at 0; > 0 is a
      misspecification check (ranks of the gains then show its effect).
    test_traj: unseen test pulls per data set (fresh profiles, same noise); > 0 adds the share
      of noisy test points inside the 95% predictive band (simulation + fitted noise,
      :func:`treeinfer.metrics.noisy_predictive_interval`) and the parameter band.
    """

    datasets: int = 20
    likelihood: str = "gaussian"
    noise_displacement: float | None = None
    noise_prior_center: float = 0.002
    sigma_prior_scale: float = 0.5
    student_t_df: float = 4.0
    sampler: str = "mh"
    particles: int = 32
    iterations: int = 200
    learning_rate: float = 0.1
    mh_warmup: int = 400
    mh_steps: int = 400
    n_traj: int = 5
    duration: float = 3.0
    dt: float = 0.01
    seed: int = 0
    max_sim_dt: float | None = None
    prior_sigma: float = 0.1
    chunk: int = 8
    rel_step: float | None = None
    backend: str = "auto"
    noise_force: float = 0.0
    test_traj: int = 0

    def check(self) -> SBCConfig:
        from .inference import check_count
        from .noise import check_df, check_sigma

        check_count(self.datasets, "datasets", 2)
        check_count(self.particles, "particles", 2)
        check_count(self.iterations, "iterations", 1)
        check_count(self.mh_steps, "mh_steps", 1)
        check_count(self.mh_warmup, "mh_warmup", 0)
        check_count(self.n_traj, "n_traj", 1)
        check_count(self.chunk, "chunk", 1)
        check_count(self.test_traj, "test_traj", 0)
        if not (isinstance(self.noise_force, (int, float)) and 0.0 <= self.noise_force < 1.0):
            raise ConfigError(f"noise_force: must be a share in [0, 1), got {self.noise_force!r}")
        if self.likelihood not in SBC_LIKELIHOODS:
            raise ConfigError(
                f"likelihood: calibrate supports {', '.join(SBC_LIKELIHOODS)} (a generative noise "
                f"model to simulate from), got {self.likelihood!r}"
            )
        if self.sampler not in SBC_SAMPLERS:
            raise ConfigError(
                f"sampler: calibrate supports {', '.join(SBC_SAMPLERS)}, got {self.sampler!r}"
            )
        if self.noise_displacement is not None:
            check_sigma(self.noise_displacement, "noise_displacement")
        check_sigma(self.noise_prior_center, "noise_prior_center")
        for name in ("sigma_prior_scale", "learning_rate", "duration", "dt", "prior_sigma"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ConfigError(f"{name}: must be a finite positive number, got {v!r}")
        if self.likelihood == "student_t":
            check_df(self.student_t_df)
        if self.duration < 5 * self.dt:
            raise ConfigError(f"duration: {self.duration} s is shorter than 5 samples of dt")
        return self


def _labels(tree, infer_sigma: bool) -> tuple[str, ...]:
    return tuple(tree.parameter_labels()) + (("sigma_x",) if infer_sigma else ())


def draw_truths(tree, config: SBCConfig, rng: np.random.Generator, n: int) -> np.ndarray:
    """``[n, D]`` prior draws in theta units: log gains from the smoothed box, then
    ``log sigma_x`` from its Normal prior when sigma_x is inferred."""
    lo, hi = np.log(tree.bounds_array()[0]), np.log(tree.bounds_array()[1])
    gains = sample_smoothed_box(rng, lo, hi, config.prior_sigma * (hi - lo), n)
    if config.noise_displacement is not None:
        return gains
    ls = rng.normal(math.log(config.noise_prior_center), config.sigma_prior_scale, size=(n, 1))
    return np.concatenate([gains, ls], axis=1)


def _build_program(sim, tree, config: SBCConfig, dim: int):
    """The jitted ``(keys [C], theta0 [C, P, D], forces [C, B, T], x_obs [C, B, T]) ->
    (draws [C, P, D], info)``: the sampler's whole scan ``vmap``-ed over C data sets."""
    import jax
    import jax.numpy as jnp
    import optax

    from . import noise as _noise
    from .gradients import autodiff_value_and_grad, finite_difference_jvp
    from .likelihood import gains_from_theta
    from .priors import smoothed_box
    from .samplers import svgd
    from .sim import simulate

    r = sim.n_joints
    lo, hi = np.log(tree.bounds_array()[0]), np.log(tree.bounds_array()[1])
    box = smoothed_box(lo, hi, config.prior_sigma * (hi - lo))
    infer_sigma = config.noise_displacement is None
    sigma_prior = (
        _noise.log_sigma_prior(config.noise_prior_center, config.sigma_prior_scale)
        if infer_sigma
        else None
    )
    kind, df = config.likelihood, float(config.student_t_df)
    n_mh = int(config.mh_steps)
    n_warm = int(config.mh_warmup)

    def log_density(theta, forces, x_obs):  # theta [P, D] -> [P]
        def rollout(th):  # black box [M, 2R] -> tau [M, B, T] (NaN where unstable)
            kp, kd = gains_from_theta(th, r)
            ro = simulate(sim, kp, kd, forces)
            return jnp.where(ro.stable[..., None], ro.tau, jnp.nan)

        tau = finite_difference_jvp(rollout, config.rel_step)(theta[:, : 2 * r])
        if infer_sigma:
            sx = jnp.exp(theta[:, 2 * r])
            lp_extra = sigma_prior(theta[:, 2 * r])
        else:
            sx = jnp.full(theta.shape[:1], config.noise_displacement, tau.dtype)
            lp_extra = 0.0
        ll = jnp.sum(_noise.residual_log_prob(x_obs - tau, sx[:, None, None], kind, df), (-2, -1))
        total = ll + box(theta[:, : 2 * r]) + lp_extra
        return jnp.where(jnp.isfinite(total), total, -jnp.inf)

    def one(key, theta0, forces, x_obs):
        logp = lambda th: log_density(th, forces, x_obs)  # noqa: E731
        vg = autodiff_value_and_grad(logp)
        if config.sampler == "svgd":
            algo = svgd(vg, learning_rate=config.learning_rate)
            state = algo.init(key, theta0)
            state, _ = jax.lax.scan(
                lambda s_, _: algo.step(key, s_), state, None, length=config.iterations
            )
            x, ld = state.position, state.logdensity
            info = {"mh_acceptance": jnp.zeros(()), "mode_logdensity": jnp.max(ld)}
        else:
            x, ld, info = _ascent_then_mh(key, logp, vg, theta0)
        info["final_mean_logdensity"] = jnp.mean(jnp.where(jnp.isfinite(ld), ld, jnp.nan))
        info["n_nonfinite"] = jnp.sum(~jnp.isfinite(ld))
        return x, info

    def _ascent_then_mh(key, logp, vg, theta0):
        # 1. Adam ascent of the P starts (independent, no kernel), learning rate decaying
        #    10x..100x so the particles settle on their modes; the best one is the mode.
        sched = optax.exponential_decay(config.learning_rate, config.iterations, 0.01)
        opt = optax.adam(sched)

        def ascend(carry, _):
            th, st = carry
            _, g = vg(th)
            upd, st = opt.update(-g, st, th)
            return (optax.apply_updates(th, upd), st), None

        (th, _), _ = jax.lax.scan(
            ascend, (theta0, opt.init(theta0)), None, length=config.iterations
        )
        ld0 = logp(th)
        ld0 = jnp.where(jnp.isfinite(ld0), ld0, -jnp.inf)
        best = th[jnp.argmax(ld0)]
        # 2. P random-walk MH chains from the mode (+ a tiny jitter). Warm-up in phases: the
        #    proposal is exp(log_s) * chol(ensemble covariance of the chains), re-estimated at
        #    each phase start (first phase: 0.01 * I), log_s tuned to ~25% acceptance by a
        #    Robbins-Monro step on the chains' mean acceptance. Then mh_steps steps with a fixed
        #    proposal; the final state of every chain is one draw.
        k0, k1, k2 = jax.random.split(jax.random.fold_in(key, 7), 3)
        x = best + 1e-3 * jax.random.normal(k0, theta0.shape, theta0.dtype)
        ld = logp(x)
        ld = jnp.where(jnp.isfinite(ld), ld, -jnp.inf)

        def mh_step(carry, k, adapt):
            xs, lds, chol, log_s, n_acc = carry
            ka, kb = jax.random.split(k)
            step = jnp.exp(log_s) * (jax.random.normal(ka, xs.shape, xs.dtype) @ chol.T)
            xp = xs + step
            ldp = logp(xp)
            ldp = jnp.where(jnp.isfinite(ldp), ldp, -jnp.inf)
            ok = jnp.log(jax.random.uniform(kb, lds.shape, xs.dtype)) < ldp - lds
            rate = jnp.mean(ok)
            log_s = log_s + adapt * 0.5 * (rate - 0.25)
            return (
                jnp.where(ok[:, None], xp, xs),
                jnp.where(ok, ldp, lds),
                chol,
                log_s,
                n_acc + rate,
            ), None

        def run(carry, keys, adapt):
            return jax.lax.scan(lambda c, k: mh_step(c, k, adapt), carry, keys)[0]

        def ensemble_chol(xs):
            c = jnp.cov(xs.T) + 1e-12 * jnp.eye(dim)
            return jnp.linalg.cholesky(c)

        carry = (x, ld, 0.01 * jnp.eye(dim, dtype=x.dtype), jnp.zeros((), x.dtype), jnp.zeros(()))
        n_phase = max(1, n_warm // _WARMUP_PHASES)
        for i, kw in enumerate(jax.random.split(k1, _WARMUP_PHASES)):
            if i > 0:
                carry = (
                    carry[0],
                    carry[1],
                    ensemble_chol(carry[0]),
                    jnp.asarray(math.log(2.38 / math.sqrt(dim)), x.dtype),
                    carry[4],
                )
            carry = run(carry, jax.random.split(kw, n_phase), 1.0)
        carry = (carry[0], carry[1], ensemble_chol(carry[0]), carry[3], jnp.zeros(()))
        x, ld, _, log_s, n_acc = run(carry, jax.random.split(k2, n_mh), 0.0)
        info = {
            "mh_acceptance": n_acc / max(n_mh, 1),
            "mode_logdensity": jnp.max(ld0),
            "mh_log_scale": log_s,
        }
        return x, ld, info

    return jax.jit(jax.vmap(one))


def _simulate_truths(sim, truth, forces, r):
    """``tau [N, B, T]`` and ``stable [N]`` of each data set's truth under its forces."""
    import jax

    from .likelihood import gains_from_theta
    from .sim import simulate

    def one(th, f):
        kp, kd = gains_from_theta(th[None, : 2 * r], r)
        ro = simulate(sim, kp, kd, f)
        return ro.tau[0], jax.numpy.all(ro.stable[0])

    return jax.jit(jax.vmap(one))(truth, forces)


def run_tree_sbc(
    tree,
    config: SBCConfig,
    progress: Callable[[int, int], None] | None = None,
    log: Callable[[str], None] = lambda msg: None,
) -> SBCResult:
    """SBC of ``tree``'s posterior under ``config`` (see :class:`SBCConfig`).

    Steps: draw N truths from the prior (:func:`draw_truths`); draw fresh force profiles for each
    data set; simulate every truth (one batched call; a truth whose rollout is unstable is redrawn,
    i.e. the prior is restricted to stable parameters, as the likelihood is); add noise of the
    chosen model (numpyro's sampler, scale sigma_x); run the batched program over chunks of data
    sets; rank the truths among the P final draws. ``progress(done, total)`` after every chunk.
    Returns an :class:`SBCResult` whose ``info`` holds timings and sampler diagnostics.
    """
    import jax
    import jax.numpy as jnp

    from . import noise as _noise
    from .forces import profile_set
    from .sim import DEFAULT_MAX_SIM_DT, make_simulator
    from .synthetic import sim_tree

    config.check()
    rng = np.random.default_rng(config.seed)
    n, r = config.datasets, tree.n_inferred
    infer_sigma = config.noise_displacement is None
    labels = _labels(tree, infer_sigma)
    dim = len(labels)
    truth = draw_truths(tree, config, rng, n)
    forces = np.stack(
        [
            profile_set("mixed", config.n_traj, config.duration, config.dt, seed=rng)
            for _ in range(n)
        ]
    )
    # one simulator for all data sets, stable up to the stiffest drawn truth
    kp_max = np.max(np.exp(truth[:, :r]), axis=0)
    sim = make_simulator(
        sim_tree(tree, kp_max),
        obs_dt=config.dt,
        max_sim_dt=config.max_sim_dt or DEFAULT_MAX_SIM_DT,
        backend=config.backend,
    )
    t0 = time.perf_counter()
    tau, stable = _simulate_truths(sim, jnp.asarray(truth), jnp.asarray(forces), r)
    tau, stable = np.asarray(tau), np.asarray(stable)
    n_redrawn = 0
    for _ in range(20):  # redraw the (rare) unstable truths
        bad = np.flatnonzero(~stable)
        if bad.size == 0:
            break
        n_redrawn += bad.size
        truth[bad] = draw_truths(tree, config, rng, bad.size)
        # the simulator's step was chosen for kp_max: keep redraws below it
        truth[bad, :r] = np.minimum(truth[bad, :r], np.log(kp_max))
        t2, s2 = _simulate_truths(sim, jnp.asarray(truth[bad]), jnp.asarray(forces[bad]), r)
        tau[bad], stable[bad] = np.asarray(t2), np.asarray(s2)
    if not np.all(stable):
        raise ConfigError(
            "calibrate: prior draws keep giving unstable simulations; lower "
            "--max-sim-dt or narrow the prior box"
        )
    sigma = np.exp(truth[:, 2 * r]) if infer_sigma else np.full(n, float(config.noise_displacement))
    key = jax.random.key(config.seed)
    unit = _noise.noise_distribution(config.likelihood, 1.0, float(config.student_t_df))
    e = np.asarray(unit.sample(jax.random.fold_in(key, 1), tau.shape))
    x_obs = tau + sigma[:, None, None] * e
    forces_rec = _record_forces(forces, config.noise_force, rng)
    test = None
    if config.test_traj:
        f_test = np.stack(
            [
                profile_set("mixed", config.test_traj, config.duration, config.dt, seed=rng)
                for _ in range(n)
            ]
        )
        tau_t, st_t = _simulate_truths(sim, jnp.asarray(truth), jnp.asarray(f_test), r)
        e_t = np.asarray(unit.sample(jax.random.fold_in(key, 3), tau_t.shape))
        x_test = np.asarray(tau_t) + sigma[:, None, None] * e_t
        test = (_record_forces(f_test, config.noise_force, rng), x_test, np.asarray(st_t))
    t_sim = time.perf_counter() - t0

    # initial particles: uniform in the log box; log sigma_x uniform within +-1 of the centre
    lo, hi = np.log(tree.bounds_array()[0]), np.log(tree.bounds_array()[1])
    if infer_sigma:
        c = math.log(config.noise_prior_center)
        lo, hi = np.append(lo, c - 1.0), np.append(hi, c + 1.0)
    p = config.particles
    theta0 = lo + rng.uniform(size=(n, p, dim)) * (hi - lo)
    program = _build_program(sim, tree, config, dim)
    keys = jax.random.split(jax.random.fold_in(key, 2), n)
    draws = np.empty((n, p, dim))
    infos: list[dict] = []
    t1 = time.perf_counter()
    t_first = None
    for start in range(0, n, config.chunk):
        sl = slice(start, min(n, start + config.chunk))
        m = sl.stop - sl.start
        pad = config.chunk - m  # keep one compiled shape: pad the last chunk by repetition
        idx = np.r_[np.arange(sl.start, sl.stop), np.full(pad, sl.start, int)]
        out, info = program(
            keys[idx],
            jnp.asarray(theta0[idx]),
            jnp.asarray(forces_rec[idx]),
            jnp.asarray(x_obs[idx]),
        )
        draws[sl] = np.asarray(out)[:m]
        infos.append({k: np.asarray(v)[:m] for k, v in info.items()})
        if t_first is None:
            t_first = time.perf_counter() - t1
        if progress is not None:
            progress(sl.stop, n)
    t_inf = time.perf_counter() - t1
    info = {k: np.concatenate([d[k] for d in infos]) for k in infos[0]}
    bad_draws = ~np.all(np.isfinite(draws), axis=(1, 2))
    if np.any(bad_draws):
        log(
            f"warning: {int(bad_draws.sum())} data sets gave non-finite draws; they are ranked "
            "with their finite draws replaced by the data set's median"
        )
        for i in np.flatnonzero(bad_draws):
            med = np.nanmedian(np.where(np.isfinite(draws[i]), draws[i], np.nan), axis=0)
            draws[i] = np.where(np.isfinite(draws[i]), draws[i], med)
    extra = _crb_ratios(sim, truth, draws, forces_rec, labels, config)
    if test is not None:
        extra.update(_predictive_coverage(sim, draws, test, config, infer_sigma))
    summary_info = {
        **extra,
        "sampler": config.sampler,
        "sampler_note": (
            "Adam ascent of P starts (box prior), then P random-walk MH chains from the best "
            "mode; warm-up in phases with the chains' ensemble covariance and a scale tuned to "
            "25% acceptance; draws = final chain states after mh_steps fixed-proposal steps"
            if config.sampler == "mh"
            else "final SVGD particles as draws"
        ),
        "n_redrawn_unstable_truths": int(n_redrawn),
        "n_nonfinite_final": int(np.sum(info["n_nonfinite"])),
        "mh_acceptance_mean": float(np.mean(info["mh_acceptance"]))
        if config.sampler == "mh"
        else None,
        "mh_acceptance_min": float(np.min(info["mh_acceptance"]))
        if config.sampler == "mh"
        else None,
        "seconds_simulate_data": t_sim,
        "seconds_inference": t_inf,
        "seconds_first_chunk_incl_compile": t_first,
        "backend": sim.backend,
        "sim_dt": sim.sim_dt,
        "jax_backend": jax.default_backend(),
        "truth_units": "theta: natural log of Kp (N m/rad), Kd (N m s/rad), sigma_x (m)",
    }
    return summarize_sbc(truth, draws, labels, seed=config.seed, info=summary_info)


def _record_forces(forces, share: float, rng: np.random.Generator) -> np.ndarray:
    """Recorded forces: ``forces [N, B, T]`` plus white noise of std ``share`` times each data
    set's peak |force| (one sensor, one level per data set)."""
    if share <= 0:
        return forces
    peak = np.max(np.abs(forces), axis=(1, 2), keepdims=True)
    return forces + share * peak * rng.normal(size=forces.shape)


def _rollout_fn(sim, r):
    from .likelihood import gains_from_theta
    from .sim import simulate

    def rollout(th, f):  # th [M, >=2R], f [B, T] -> (tau [M, B, T], stable [M, B])
        kp, kd = gains_from_theta(th[:, : 2 * r], r)
        ro = simulate(sim, kp, kd, f)
        return ro.tau, ro.stable

    return rollout


def _crb_ratios(sim, truth, draws, forces_rec, labels, config: SBCConfig) -> dict:
    """Posterior std (log units, over the draws) / Cramer-Rao std at the truth, per parameter:
    median and quartiles over data sets. Fisher of the gains ``J^T J / sigma^2`` with ``J`` the
    central-difference sensitivities of the training displacements to the log gains under the
    recorded forces (:func:`treeinfer.gradients.central_difference_jacobian`); for log sigma_x
    (Gaussian) the bound is ``1 / sqrt(2 n)`` (n samples; the Fisher matrix is block diagonal).
    Only for the Gaussian likelihood (None otherwise)."""
    import jax
    import jax.numpy as jnp

    from .gradients import central_difference_jacobian

    if config.likelihood != "gaussian":
        return {"crb": None}
    r = sim.n_joints
    rollout = _rollout_fn(sim, r)

    def jac_one(th, f):
        _, j = central_difference_jacobian(
            lambda t: rollout(t, f)[0], th[None, : 2 * r], rel_step=1e-2
        )
        return j[0]  # [B, T, 2R]

    fn = jax.jit(jax.vmap(jac_one))
    n = truth.shape[0]
    crb = np.empty((n, truth.shape[1]))
    for start in range(0, n, config.chunk):
        sl = slice(start, min(n, start + config.chunk))
        j = np.asarray(fn(jnp.asarray(truth[sl]), jnp.asarray(forces_rec[sl])), float)
        j = j.reshape(j.shape[0], -1, 2 * r)
        sig = (
            np.exp(truth[sl, 2 * r])
            if config.noise_displacement is None
            else np.full(j.shape[0], config.noise_displacement)
        )
        for i in range(j.shape[0]):
            fisher = j[i].T @ j[i] / sig[i] ** 2
            crb[sl.start + i, : 2 * r] = np.sqrt(np.diag(np.linalg.pinv(fisher)))
        if config.noise_displacement is None:
            crb[sl, 2 * r] = 1.0 / math.sqrt(2 * j.shape[1])
    ratio = np.std(draws, axis=1, ddof=1) / crb
    q = np.nanpercentile(ratio, [25, 50, 75], axis=0)
    return {
        "crb": {
            "definition": "posterior std of the log parameter over the draws / Cramer-Rao std at "
            "the truth (Fisher J^T J / sigma^2, J by central differences on the recorded training "
            "forces; log sigma_x: 1/sqrt(2n)); quartiles over data sets",
            "parameters": {
                lab: {
                    "ratio_q25": float(q[0, k]),
                    "ratio_median": float(q[1, k]),
                    "ratio_q75": float(q[2, k]),
                    "crb_log_std_median": float(np.median(crb[:, k])),
                }
                for k, lab in enumerate(labels)
            },
        }
    }


def _predictive_coverage(sim, draws, test, config: SBCConfig, infer_sigma: bool) -> dict:
    """Share of noisy unseen test points inside the 95% predictive band (draws' simulations
    under the recorded test forces + their noise model) and inside the parameter-only band,
    per data set (median, quartiles, pooled)."""
    import jax
    import jax.numpy as jnp

    from .metrics import predictive_bands

    f_test, x_test, st_truth = test
    r = sim.n_joints
    fn = jax.jit(jax.vmap(_rollout_fn(sim, r)))
    n = draws.shape[0]
    inside_pred = np.full(n, np.nan)
    inside_par = np.full(n, np.nan)
    for start in range(0, n, config.chunk):
        sl = slice(start, min(n, start + config.chunk))
        tau, stable = fn(jnp.asarray(draws[sl]), jnp.asarray(f_test[sl]))
        tau, stable = np.asarray(tau), np.asarray(stable)
        for i in range(tau.shape[0]):
            d = sl.start + i
            valid = np.all(stable[i], axis=-1)
            if valid.sum() < 2 or not np.all(st_truth[d]):
                continue
            s = np.exp(draws[d, :, 2 * r]) if infer_sigma else float(config.noise_displacement)
            kind = "student_t" if config.likelihood == "student_t" else "gaussian"
            bands = predictive_bands(tau[i], s, 0.95, valid, kind, float(config.student_t_df))
            x = x_test[d]
            inside_pred[d] = np.mean(
                (x >= np.asarray(bands.predictive.lower))
                & (x <= np.asarray(bands.predictive.upper))
            )
            inside_par[d] = np.mean(
                (x >= np.asarray(bands.parameter.lower)) & (x <= np.asarray(bands.parameter.upper))
            )

    def stats(v):
        q = np.nanpercentile(v, [25, 50, 75])
        return {
            "mean": float(np.nanmean(v)),
            "q25": float(q[0]),
            "median": float(q[1]),
            "q75": float(q[2]),
            "n_datasets": int(np.sum(np.isfinite(v))),
        }

    return {
        "test_inside_95": {
            "definition": f"share of the {config.test_traj} noisy unseen test pulls' points inside "
            "the 95% band per data set; predictive = simulations + fitted noise "
            "(metrics.predictive_bands), parameter = simulations only",
            "noise_force_share": config.noise_force,
            "predictive": stats(inside_pred),
            "parameter": stats(inside_par),
        }
    }


def config_record(tree_path, config: SBCConfig) -> dict:
    """``config.json`` content: every option, the seed and versions."""
    from .runs.provenance import versions

    return {
        "command": "calibrate",
        "tree": str(tree_path),
        "options": asdict(config),
        "versions": versions(extended=True),
    }
