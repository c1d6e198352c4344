"""One visit's posterior as the next visit's prior.

Bayes' rule applied twice gives the same posterior as once on all the data:
``p(theta | A, B) ∝ p(theta | A) p(B | theta)``. We cannot carry ``p(theta | A)`` itself, only
its particles ``theta_A [P, D]`` (``log Kp``, ``log Kd``), so the next run gets a density
*fitted* to them, as a log-density term ``theta [N, D] -> [N]`` that composes with the other
terms (:func:`treeinfer.model.gradients.combine`) and is differentiable (exact autodiff gradients).

**The density: a Gaussian mixture fitted by EM** (:func:`fit_gaussian_mixture`), the number of
components (1..``max_components``) chosen by BIC, in theta (log) space. Why not a kernel density
estimate: a KDE's covariance is the particles' covariance *plus* the kernel's (Scott's rule,
``h = n^(-1/(d+4))``: +35% variance at 64 particles in 4 dimensions), so every visit would
widen the prior, and the widening compounds over visits. The maximum-likelihood mixture matches
the particles' mean and covariance exactly (EM's M-step is moment matching; the one-component
fit *is* the sample mean and covariance, ``ddof=0``), so a Gaussian-shaped posterior carries
over without loss, and extra components are chosen only when the particles clearly show skew
or several modes (a few dozen particles rarely support more than one in 4-6 dimensions).
The EM is written here (a few lines of numpy) because scikit-learn is not a dependency.

**Shared joints.** The mixture is fitted on all of the earlier run's coordinates and
marginalised (exactly: a mixture's marginal is the mixture of the components' marginals) onto
the labels the two runs share (``Kp[joint]``, ``Kd[joint]``), reordered to the new run's
columns (:func:`map_labels`). The other coordinates of the new run keep the box prior alone.

**Uninformed coordinates.** Where the earlier posterior is as wide as the prior box (its std
at least 0.8 of a uniform's on the box, :func:`uninformed_labels`), a Gaussian fit would put a
bump in the box's middle that the data never asked for; given the earlier run's box, such
coordinates keep the box alone (their correlations with the others are dropped).

**Effect on intervals.** The new problem keeps its smoothed box on every coordinate (it is flat
inside the box, so inside the box the prior of a shared coordinate is the fitted density, as
the earlier posterior already included the box). The reported credible intervals of the next
run are those of ``fitted prior x new likelihood``: narrower than a fresh run's wherever the
earlier data were informative; when the earlier posterior was skewed against a box edge, the
Gaussian fit has a symmetric tail there, which the box cuts off again. With few particles the
fit's covariance is itself noisy (relative error ~ ``sqrt(2 / P)`` on each variance), which
passes on to the next run's intervals. The NN inequality prior of an earlier NNSVGD run is
already inside its particles: build the next problem with ``nn_prior=False`` to count it once.

Use::

    prior = prior_from_particles(run_a.theta, run_a.labels, problem_b.labels, valid=run_a.stable)
    posterior_b = infer(with_prior(problem_b, prior.log_density), sampler="svgd")
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import logsumexp
from jax.scipy.stats import multivariate_normal

from ..errors import ConfigError
from ..model.gradients import autodiff_value_and_grad, combine, mask_nonfinite

__all__ = [
    "GaussianMixture",
    "SequentialPrior",
    "fit_gaussian_mixture",
    "map_labels",
    "prior_from_particles",
    "prior_from_run",
    "uninformed_labels",
    "with_prior",
]


class GaussianMixture(NamedTuple):
    """A Gaussian mixture in theta space.

    weights: [K] (sum 1). means: [K, D]. covariances: [K, D, D] (theta units squared).
    labels: the D coordinate labels. log_likelihood: mean log-density of the fitted points
    (nats per point). bic: Bayesian information criterion of the fit (lower is better).
    """

    weights: np.ndarray
    means: np.ndarray
    covariances: np.ndarray
    labels: tuple[str, ...]
    log_likelihood: float = float("nan")
    bic: float = float("nan")

    @property
    def n_components(self) -> int:
        return len(self.weights)

    def marginal(self, labels: Sequence[str]) -> GaussianMixture:
        """The exact marginal on ``labels`` (in that order)."""
        missing = [lab for lab in labels if lab not in self.labels]
        if missing:
            raise ConfigError(f"mixture: no coordinate(s) {missing}; it has {list(self.labels)}")
        idx = np.array([self.labels.index(lab) for lab in labels], int)
        return GaussianMixture(
            self.weights,
            self.means[:, idx],
            self.covariances[:, idx][:, :, idx],
            tuple(labels),
            float("nan"),
            float("nan"),
        )

    def log_density(self, columns: Sequence[int] | None = None):
        """Log-density term ``theta [N, D'] -> [N]`` of the mixture on ``theta[:, columns]``
        (default: all columns, in order). Differentiable; normalised."""
        w = jnp.log(jnp.asarray(self.weights, jnp.float32))
        mu = jnp.asarray(self.means, jnp.float32)
        cov = jnp.asarray(self.covariances, jnp.float32)
        cols = None if columns is None else np.asarray(columns, int)
        dim = self.means.shape[1]

        def logdensity(theta):
            theta = jnp.asarray(theta)
            x = theta if cols is None else theta[:, cols]
            if x.shape[-1] != dim:
                raise ConfigError(
                    f"fitted prior: expects {dim} coordinates, got theta of shape {theta.shape}"
                )
            comp = jax.vmap(lambda m, c: multivariate_normal.logpdf(x, m, c))(
                mu.astype(x.dtype), cov.astype(x.dtype)
            )
            return logsumexp(comp + w[:, None].astype(x.dtype), axis=0)

        return logdensity

    def to_dict(self) -> dict:
        return {
            "labels": list(self.labels),
            "weights": self.weights.tolist(),
            "means": self.means.tolist(),
            "covariances": self.covariances.tolist(),
            "log_likelihood_per_point": self.log_likelihood,
            "bic": self.bic,
        }


# ==== EM ==========================================================================================
def _logpdf_np(x, mean, cov):
    """log N(x; mean, cov) [N] (numpy, Cholesky)."""
    lc = np.linalg.cholesky(cov)
    z = np.linalg.solve(lc, (x - mean).T)
    return (
        -0.5 * np.sum(z**2, 0)
        - np.sum(np.log(np.diag(lc)))
        - 0.5 * x.shape[1] * math.log(2 * math.pi)
    )


def _n_params(k: int, d: int) -> int:
    return k * (d + d * (d + 1) // 2) + (k - 1)


def _em(x: np.ndarray, k: int, reg: np.ndarray, n_iter: int, tol: float, rng: np.random.Generator):
    n, d = x.shape
    # k-means++-style seeding of the means; shared starting covariance
    means = [x[rng.integers(n)]]
    for _ in range(1, k):
        d2 = np.min([np.sum((x - m) ** 2, 1) for m in means], axis=0)
        means.append(x[rng.choice(n, p=d2 / d2.sum())])
    means = np.array(means)
    covs = np.repeat((np.cov(x, rowvar=False, bias=True).reshape(d, d) + reg)[None], k, 0)
    weights = np.full(k, 1.0 / k)
    prev = -np.inf
    for _ in range(n_iter):
        logp = np.stack(
            [np.log(weights[j]) + _logpdf_np(x, means[j], covs[j]) for j in range(k)], 1
        )
        top = logp.max(1, keepdims=True)
        norm = top[:, 0] + np.log(np.exp(logp - top).sum(1))
        ll = float(norm.mean())
        resp = np.exp(logp - norm[:, None])  # [N, K]
        nk = resp.sum(0) + 1e-12
        weights = nk / n
        means = (resp.T @ x) / nk[:, None]
        for j in range(k):
            dx = x - means[j]
            covs[j] = (resp[:, j, None] * dx).T @ dx / nk[j] + reg
        if ll - prev < tol * max(1.0, abs(ll)):
            break
        prev = ll
    logp = np.stack([np.log(weights[j]) + _logpdf_np(x, means[j], covs[j]) for j in range(k)], 1)
    top = logp.max(1, keepdims=True)
    ll = float((top[:, 0] + np.log(np.exp(logp - top).sum(1))).mean())
    return weights, means, covs, ll


def fit_gaussian_mixture(
    x,
    labels: Sequence[str] | None = None,
    n_components: int | None = None,
    max_components: int = 3,
    reg_covar: float = 1e-6,
    n_iter: int = 300,
    tol: float = 1e-7,
    n_init: int = 3,
    seed: int = 0,
) -> GaussianMixture:
    """Fit a full-covariance Gaussian mixture to ``x [N, D]`` by EM (maximum likelihood).

    ``n_components=None`` fits 1..``max_components`` and keeps the lowest BIC (counts for which
    ``N`` is below twice the number of free parameters are skipped). ``K = 1`` is the sample
    mean and covariance (``ddof=0``) in closed form. ``reg_covar`` is added to every
    covariance's diagonal, relative to each coordinate's variance (numerical safety only).
    ``n_init`` seeded restarts per ``K > 1``, the best likelihood kept.
    """
    x = np.asarray(x, float)
    if x.ndim != 2 or x.shape[0] < 2 or not np.all(np.isfinite(x)):
        raise ConfigError(f"particles: need a finite [N, D] array with N >= 2, got shape {x.shape}")
    n, d = x.shape
    labels = tuple(labels) if labels is not None else tuple(f"theta[{i}]" for i in range(d))
    if len(labels) != d:
        raise ConfigError(f"particles: {d} columns but {len(labels)} labels")
    if n_components is not None:
        if (
            isinstance(n_components, bool)
            or not isinstance(n_components, (int, np.integer))
            or n_components < 1
        ):
            raise ConfigError(f"n_components: must be a positive integer, got {n_components!r}")
        ks = [int(n_components)]
    else:
        ks = [k for k in range(1, int(max_components) + 1) if k == 1 or n >= 2 * _n_params(k, d)]
    var = np.var(x, 0)
    if np.any(var <= 0):
        raise ConfigError(
            f"particles: coordinate(s) {np.nonzero(var <= 0)[0].tolist()} do not vary; "
            "cannot fit a density"
        )
    reg = np.diag(reg_covar * var)
    rng = np.random.default_rng(seed)
    best = None
    for k in ks:
        if k == 1:
            mean = x.mean(0)
            cov = np.cov(x, rowvar=False, bias=True).reshape(d, d) + reg
            fit = (np.ones(1), mean[None], cov[None], float(_logpdf_np(x, mean, cov).mean()))
        else:
            fits = [_em(x, k, reg, n_iter, tol, rng) for _ in range(n_init)]
            fit = max(fits, key=lambda f: f[3])
        bic = -2 * n * fit[3] + _n_params(k, d) * math.log(n)
        if best is None or bic < best[1]:
            best = (fit, bic)
    (w, m, c, ll), bic = best
    return GaussianMixture(np.asarray(w), np.asarray(m), np.asarray(c), labels, ll, float(bic))


# ==== the sequential prior ========================================================================
def map_labels(
    labels_prev: Sequence[str], labels_new: Sequence[str]
) -> tuple[list[str], list[int], list[str]]:
    """``(shared, columns, box_only)``: the labels of the new run that the earlier run also
    inferred (new-run order), their column indices in the new theta, and the new labels that keep
    the box prior alone. Raises :class:`ConfigError` when the runs share no parameter."""
    prev = set(labels_prev)
    shared = [lab for lab in labels_new if lab in prev]
    if not shared:
        raise ConfigError(
            f"prior run: shares no parameter with this run (earlier: {list(labels_prev)}; "
            f"now: {list(labels_new)})"
        )
    cols = [list(labels_new).index(lab) for lab in shared]
    return shared, cols, [lab for lab in labels_new if lab not in prev]


class SequentialPrior(NamedTuple):
    """The earlier run's posterior as a prior term of the new run.

    mixture: the fitted mixture, marginalised onto ``shared`` (new-run order). full_mixture: the
    fit on all the earlier run's coordinates. shared: labels given the fitted prior; columns:
    their indices in the new theta; box_only: labels that keep the box prior alone (not in the
    earlier run, or uninformed there). log_density: ``theta [N, D_new] -> [N]``. n_particles:
    particles fitted. uninformed: shared labels the earlier data left at the box.
    """

    mixture: GaussianMixture
    full_mixture: GaussianMixture
    shared: tuple[str, ...]
    columns: tuple[int, ...]
    box_only: tuple[str, ...]
    n_particles: int
    uninformed: tuple[str, ...] = ()

    @property
    def log_density(self):
        return self.mixture.log_density(self.columns)

    def to_dict(self) -> dict:
        """JSON record (for the new run's config)."""
        return {
            "density": "gaussian_mixture",
            "n_components": self.mixture.n_components,
            "n_particles": self.n_particles,
            "shared": list(self.shared),
            "box_only": list(self.box_only),
            "uninformed": list(self.uninformed),
            "mixture": self.mixture.to_dict(),
            "bic": self.full_mixture.bic,
        }


UNINFORMED_SHARE = 0.8  # a marginal this wide (share of the box's uniform std) counts as uninformed


def uninformed_labels(
    theta, labels: Sequence[str], lower, upper, share: float = UNINFORMED_SHARE
) -> list[str]:
    """Labels whose particle std is at least ``share`` of the std of a uniform on the box
    ``[lower, upper]`` (``(upper - lower) / sqrt(12)``): the earlier data left them at the prior.

    Such coordinates are better served by the box alone than by a Gaussian fitted to a flat
    marginal (which would put a bump in the box's middle: at the box edge a Gaussian of the
    uniform's std is down to exp(-1.5) = 0.22 of its peak)."""
    theta = np.asarray(theta, float)
    width = (np.asarray(upper, float) - np.asarray(lower, float)) / math.sqrt(12.0)
    return [lab for lab, s, w in zip(labels, theta.std(0), width) if s >= share * w]


def prior_from_particles(
    theta_prev,
    labels_prev: Sequence[str],
    labels_new: Sequence[str],
    valid=None,
    box: tuple | None = None,
    uninformed_share: float = UNINFORMED_SHARE,
    **fit_options,
) -> SequentialPrior:
    """Fit the earlier posterior's particles ``theta_prev [P, D_prev]`` (columns
    ``labels_prev``) and return the prior term for a run with columns ``labels_new``.

    valid: [P] particles to keep (e.g. the earlier run's stable ones; non-finite rows are
    always dropped). box: ``(lower [D_prev], upper [D_prev])``, the earlier run's prior box in
    theta units; when given, shared coordinates the earlier data left uninformed
    (:func:`uninformed_labels`) keep the box alone, which loses their correlation with the
    others (small when the marginal is as wide as the box). ``fit_options`` go to
    :func:`fit_gaussian_mixture`."""
    theta = np.asarray(theta_prev, float)
    if theta.ndim != 2 or theta.shape[1] != len(labels_prev):
        raise ConfigError(
            f"prior run: particles of shape {theta.shape} do not match {len(labels_prev)} labels"
        )
    ok = np.all(np.isfinite(theta), 1)
    if valid is not None:
        ok &= np.asarray(valid, bool)
    shared, cols, box_only = map_labels(labels_prev, labels_new)
    uninformed: list[str] = []
    if box is not None:
        uninformed = [
            lab
            for lab in uninformed_labels(theta[ok], labels_prev, *box, share=uninformed_share)
            if lab in shared
        ]
        if len(uninformed) == len(shared):
            raise ConfigError(
                f"prior run: its posterior is as wide as the prior box in every shared parameter "
                f"({uninformed}); it carries no information to pass on"
            )
        keep = [i for i, lab in enumerate(shared) if lab not in uninformed]
        shared, cols = [shared[i] for i in keep], [cols[i] for i in keep]
        box_only = [lab for lab in labels_new if lab not in shared]
    full = fit_gaussian_mixture(theta[ok], labels=labels_prev, **fit_options)
    return SequentialPrior(
        full.marginal(shared),
        full,
        tuple(shared),
        tuple(cols),
        tuple(box_only),
        int(ok.sum()),
        tuple(uninformed),
    )


def prior_from_run(run, labels_new: Sequence[str], **fit_options) -> SequentialPrior:
    """:func:`prior_from_particles` of a finished run (its final particles, stable ones only).

    ``run``: the posterior of a run, as :func:`treeinfer.runs.load_run` returns it (anything
    with ``theta [P, D]``, ``labels``, ``stable [P]`` and ``tree``). It takes the loaded run, not
    its folder, so that this module does not import :mod:`treeinfer.runs` (which imports it:
    the run's configuration may name an earlier run as its prior)."""
    lo, hi = run.tree.bounds_array()
    box = (np.log(lo), np.log(hi))
    return prior_from_particles(
        run.theta, run.labels, labels_new, valid=run.stable, box=box, **fit_options
    )


def with_prior(problem, *terms):
    """``problem`` with extra prior log-density ``terms`` (each ``theta [N, D] -> [N]``,
    differentiable) added to its target: a new :class:`~treeinfer.inference.problem.Problem` whose
    ``value_and_grad``, ``log_density`` and ``log_prior`` include them (exact autodiff gradients
    for the terms)."""
    if not terms:
        return problem
    extra = combine(*terms)
    extra_vg = autodiff_value_and_grad(extra)
    base_vg = problem.value_and_grad

    def value_and_grad(theta):
        (a, ga), (b, gb) = base_vg(theta), extra_vg(theta)
        return mask_nonfinite(a + b, ga + gb)

    settings = {
        **problem.settings,
        "extra_prior_terms": problem.settings.get("extra_prior_terms", 0) + len(terms),
    }
    return dataclasses.replace(
        problem,
        value_and_grad=value_and_grad,
        log_density=combine(problem.log_density, extra),
        log_prior=combine(problem.log_prior, extra),
        settings=settings,
    )
