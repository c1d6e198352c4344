"""The MAP and Laplace approximation of a static model's posterior from EXACT derivatives.

The static model's equilibrium is differentiable to any order at the cost of one linear solve
per sample (:mod:`~treeinfer.inference.static.equilibrium`: the implicit function theorem through
``lax.custom_root``), so its log-density has an exact gradient and Hessian by autodiff. The
generic :func:`treeinfer.inference.laplace.problem_laplace` (L-BFGS-B, then a Hessian from
differences of values with steps a hundredth of each prior box) serves black-box models; on a
soft-tied stem chain its steps are hundreds of posterior widths in the scale (the box spans 3
decades, the data pin the scale to ~1e-3 in log units) and its MAP stops short: the stem study's
folds then started MH from a covariance 10x too wide in ``log sigma_x`` (0.52 against 0.05), the
chains accepted 0.3% of their moves and R-hat stayed at 2-5 (``experiments/README.md``, stem
section).

:func:`exact_laplace`: the best of uniform starts, L-BFGS-B on the problem's own gradient, then
Newton's method (scipy ``trust-exact``, the Hessian from differences of the exact gradient) to
the MAP, and the covariance ``(-H)^-1`` there.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import ConfigError
from ..laplace import ProblemLaplace, _values, best_local_fit


def exact_laplace(
    problem,
    n_starts: int = 64,
    n_local: int = 2,
    seed: int = 0,
    max_iterations: int = 200,
    gtol: float = 1e-4,
) -> ProblemLaplace:
    """MAP and Laplace covariance of a problem with a differentiable log-density.

    Args:
      problem: a :class:`~treeinfer.inference.problem.Problem` whose ``log_density`` is
      differentiable
        by JAX (the static model with a generative likelihood: the Gaussian or Student-t, any
        layout, tie or load-cell term); theta ``[D]``. Build it with ``gradient="autodiff"``:
        with ``"fd"`` the simulation carries a central-difference rule (2D + 1 equilibria per
        gradient, ~30x the cost, and only approximate).
      n_starts, n_local, seed: the best ``n_local`` of ``n_starts`` uniform points of the prior
        box (one batched call) are polished by L-BFGS-B on the problem's ``value_and_grad``.
      max_iterations: per local fit (each stage).
      gtol: ``trust-exact``'s gradient tolerance (nats per theta unit).

    Returns:
      :class:`treeinfer.inference.laplace.ProblemLaplace`: ``theta`` the MAP, ``cov = (-H)^-1`` with
      H the Hessian of the log-density there (central differences of the exact gradient; a
      saddle raises), ``steps`` zeros, ``n_evals`` log-density and derivative evaluations.

    Raises:
      ConfigError: no start with a finite log-density, or the Hessian at the end point is not
        negative definite (not a maximum: the posterior is improper along some direction).
    """
    from scipy.optimize import minimize

    lower, upper = np.asarray(problem.lower, float), np.asarray(problem.upper, float)
    width = upper - lower
    starts = lower + np.random.default_rng(seed).random((max(1, int(n_starts)), lower.size)) * width
    f0 = _values(problem, starts)
    if not np.any(np.isfinite(f0)):
        raise ConfigError("Laplace start: no finite log-density in the prior box")
    n_evals = len(starts)
    dtype = problem.sim.dtype if getattr(problem, "sim", None) is not None else jnp.float32

    def one(x):  # [D] -> scalar log-density
        return problem.log_density(x[None])[0]

    value_grad = jax.jit(jax.value_and_grad(one))
    # per-point gradients of a batch [N, D] -> [N, D]: the points are independent
    batch_grad = jax.jit(jax.grad(lambda x: jnp.sum(problem.log_density(x))))

    def hessian(x):
        """Central differences of the exact gradient (one batched call of 2D points), steps
        ``1e-3`` in theta units, symmetrised: second-order autodiff through the equilibrium's
        implicit derivatives costs ~40x a gradient here (and minutes to compile)."""
        d = x.size
        h = 1e-3
        pts = np.concatenate([x + h * np.eye(d), x - h * np.eye(d)])
        g = np.asarray(batch_grad(jnp.asarray(pts, dtype)), float)
        hess = (g[:d] - g[d:]) / (2 * h)  # row i: d grad / d x_i
        return 0.5 * (hess + hess.T)

    def objective(x):
        v, g = value_grad(jnp.asarray(x, dtype))
        v, g = float(v), np.asarray(g, float)
        if not (np.isfinite(v) and np.all(np.isfinite(g))):
            return 1e30, np.zeros_like(x)
        return -v, -g

    def neg_hess(x):
        return -hessian(np.asarray(x, float))

    bounds = list(zip(lower - 0.5 * width, upper + 0.5 * width))
    order = np.argsort(-f0)[: max(1, int(n_local))]
    best, n_fit = best_local_fit(objective, starts, f0, order, bounds, max_iterations)
    n_evals += n_fit
    # Newton with the Hessian (trust region): L-BFGS-B stops early on a posterior whose
    # widths span three decades
    res = minimize(
        objective,
        best.x,
        jac=True,
        hess=neg_hess,
        method="trust-exact",
        options={"maxiter": int(max_iterations), "gtol": float(gtol)},
    )
    n_evals += int(res.nfev) + int(res.get("nhev", 0))
    theta = np.asarray(res.x if res.fun <= best.fun else best.x, float)
    prec = neg_hess(theta)
    prec = 0.5 * (prec + prec.T)
    w = np.linalg.eigvalsh(prec)
    if not (np.all(np.isfinite(w)) and w.min() > 0):
        raise ConfigError(
            f"Laplace: the Hessian at the fitted point is not negative definite (eigenvalues "
            f"of -H from {w.min():.3g} to {w.max():.3g}); the posterior has no proper mode there"
        )
    cov = np.linalg.inv(prec)
    return ProblemLaplace(
        theta, 0.5 * (cov + cov.T), -float(min(res.fun, best.fun)), np.zeros_like(theta), n_evals
    )
