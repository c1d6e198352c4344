"""The noise scale's prior (issue 27, item 1): weakly informative over decades, from the
sensor's resolution to the data's range, and the box samplers see is that range. References:
scipy quadrature for the normalisation, closed forms for the bounds, and a clean and a noisy
recording whose sigma posteriors (on a grid, scipy) both lie inside the flat part."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate, stats

from treeinfer.data.trajectories import Trajectory
from treeinfer.model import noise


def _trajs(sigma, q=None, n=3, T=301, dt=0.01, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(T) * dt
    out = []
    for b in range(n):
        x = 0.04 * (1 - np.exp(-3 * t)) * (1 + 0.2 * b) + sigma * rng.standard_normal(T)
        if q is not None:
            x = q * np.round(x / q)
        out.append(Trajectory(t, np.ones(T), x, None, f"p{b}"))
    return out


def test_prior_spans_resolution_to_range_and_is_normalised():
    trajs = _trajs(2e-3)
    p = noise.noise_scale_prior(trajs)
    rng = max(np.ptp(t.displacement) for t in trajs)  # one pull's range is the smallest
    allx = np.concatenate([t.displacement for t in trajs])
    assert p.floor == noise.RESOLUTION_FLOOR and p.rule == "resolution floor"
    assert p.ceiling == pytest.approx(np.ptp(allx))
    assert p.ceiling >= rng
    assert p.lower_tail == pytest.approx(0.5 / math.sqrt(3 * 301))
    lo, hi = p.log_bounds

    def dens(s):
        return float(np.exp(p.log_prob(jnp.asarray(s))))

    total = sum(
        integrate.quad(dens, a, b, limit=200)[0] for a, b in ((lo - 1, lo), (lo, hi), (hi, hi + 12))
    )
    assert total == pytest.approx(1.0, rel=1e-3)
    inside = np.asarray(p.log_prob(jnp.linspace(lo, hi, 7)))
    np.testing.assert_allclose(inside, inside[0], atol=1e-9)  # flat over the decades
    # the tails: Gaussian, scipy's normal log density up to the constant
    s = np.array([lo - 0.05, hi + 0.7])
    got = np.asarray(p.log_prob(jnp.asarray(s))) - inside[0]
    ref = [
        stats.norm.logpdf(s[0], lo, p.lower_tail) - stats.norm.logpdf(lo, lo, p.lower_tail),
        stats.norm.logpdf(s[1], hi, p.upper_tail) - stats.norm.logpdf(hi, hi, p.upper_tail),
    ]
    np.testing.assert_allclose(got, ref, rtol=1e-5)


def test_quantised_recording_floors_the_prior_at_step_over_sqrt12():
    p = noise.noise_scale_prior(_trajs(1e-4, q=5e-4))
    assert p.floor == pytest.approx(5e-4 / math.sqrt(12))
    assert "quantisation step" in p.rule


def _grid_posterior_sigma(trajs, p):
    """Posterior of log sigma for residuals known exactly (the truth's), on a grid: the data's
    pull on sigma against this prior (scipy densities)."""
    t = np.arange(301) * 0.01
    r = np.concatenate(
        [tr.displacement - 0.04 * (1 - np.exp(-3 * t)) * (1 + 0.2 * b) for b, tr in
         enumerate(trajs)]
    )  # fmt: skip
    grid = np.linspace(math.log(1e-7), math.log(1.0), 4001)
    lp = np.array([stats.norm.logpdf(r, scale=math.exp(g)).sum() for g in grid])
    lp = lp + np.asarray(p.log_prob(jnp.asarray(grid)))
    return grid[int(np.argmax(lp))]


@pytest.mark.parametrize("sigma", [2e-4, 3e-3])
def test_clean_and_noisy_recordings_put_sigma_inside_the_flat_part(sigma):
    """A near-clean recording (0.2 mm, the model-error scale of the issue's clean case) and a
    noisy one (3 mm): the sigma MAP sits at the truth, inside the prior's flat part, far from
    either end (the old prior's box, the estimate +-1 in log, was left by the clean case)."""
    trajs = _trajs(sigma, seed=1)
    p = noise.noise_scale_prior(trajs)
    mode = _grid_posterior_sigma(trajs, p)
    lo, hi = p.log_bounds
    assert math.exp(mode) == pytest.approx(sigma, rel=0.1)
    assert lo + 1 < mode < hi - 1


def test_noise_free_record_keeps_sigma_near_the_floor():
    """Residuals of 1e-9 m (an exact model): the likelihood pulls log sigma down by n nats per
    e-fold, the steep lower tail holds the mode within exp(0.3) of the floor."""
    trajs = _trajs(1e-9, seed=2)
    p = noise.noise_scale_prior(trajs)
    mode = _grid_posterior_sigma(trajs, p)
    assert abs(mode - math.log(p.floor)) < 0.3
