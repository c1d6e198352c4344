"""Smoothed box prior and neural-network inequality prior."""

import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate

from treeinfer.errors import ConfigError
from treeinfer.model import priors
from treeinfer.model.gradients import autodiff_value_and_grad
from treeinfer.model.priors import (
    inequality_prior,
    inequality_target,
    load_or_train_inequality_network,
    smoothed_box,
    train_inequality_network,
)

LOWER = np.array([0.0, -2.0, 1.0])
UPPER = np.array([1.0, 3.0, 1.5])
SIGMA = np.array([0.1, 0.5, 0.2])


def box_reference(theta):
    """Independent closed form: distance to the box per coordinate, numpy."""
    theta = np.asarray(theta, np.float64)
    dist = np.where(theta < LOWER, LOWER - theta, np.where(theta > UPPER, theta - UPPER, 0.0))
    return -np.sum(dist**2 / (2 * SIGMA**2), axis=-1)


# ---------------------------------------------------------------- smoothed box


def test_smoothed_box_flat_inside_with_zero_gradient():
    logp = smoothed_box(LOWER, UPPER, SIGMA)
    inside = jax.random.uniform(jax.random.key(0), (50, 3), minval=LOWER, maxval=UPPER)
    value, grad = autodiff_value_and_grad(logp)(inside)
    np.testing.assert_array_equal(value, 0.0)
    np.testing.assert_array_equal(grad, 0.0)


def test_smoothed_box_tails_match_closed_form():
    logp = smoothed_box(LOWER, UPPER, SIGMA)
    theta = jax.random.uniform(jax.random.key(1), (200, 3), minval=-4.0, maxval=5.0)
    np.testing.assert_allclose(logp(theta), box_reference(theta), rtol=1e-5, atol=1e-5)
    # gradient: -dist / sigma^2 pointing back into the box
    _, grad = autodiff_value_and_grad(logp)(theta)
    t = np.asarray(theta)
    ref = np.where(t < LOWER, (LOWER - t), np.where(t > UPPER, -(t - UPPER), 0.0)) / SIGMA**2
    np.testing.assert_allclose(grad, ref, rtol=1e-5, atol=1e-4)


def test_smoothed_box_gradient_continuous_at_boundary():
    logp = smoothed_box(LOWER, UPPER, SIGMA)
    vg = autodiff_value_and_grad(logp)
    mid = (LOWER + UPPER) / 2
    for d in range(3):
        for edge in (LOWER[d], UPPER[d]):
            for delta in (1e-3, 1e-5):
                pts = np.tile(mid, (2, 1))
                pts[0, d], pts[1, d] = edge - delta, edge + delta
                value, grad = vg(jnp.asarray(pts))
                # both sides within delta / sigma^2 of 0 -> continuous (no jump at the edge)
                assert np.max(np.abs(grad)) <= delta / SIGMA[d] ** 2 * 1.01 + 1e-6
                assert np.max(np.abs(value)) <= delta**2 / SIGMA[d] ** 2


def test_smoothed_box_normalised_matches_gpytorch_and_integrates_to_one():
    lo, hi, s = -1.0, 2.0, 0.3
    logp = smoothed_box([lo], [hi], s, normalized=True)
    # GPyTorch: Normal(0, s).log_prob(dist) - log(1 + (hi - lo) / (sqrt(2 pi) s))
    x = np.array([-2.0, -1.0, 0.0, 2.5])
    dist = np.maximum(np.abs(x - 0.5) - 1.5, 0)
    gp = (
        -(dist**2) / (2 * s**2)
        - math.log(s * math.sqrt(2 * math.pi))
        - math.log(1 + (hi - lo) / (math.sqrt(2 * math.pi) * s))
    )
    np.testing.assert_allclose(logp(jnp.asarray(x[:, None])), gp, rtol=1e-5)
    total, _ = integrate.quad(
        lambda t: math.exp(float(logp(jnp.array([[t]]))[0])), -10, 10, points=[lo, hi]
    )
    assert total == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize(
    "args",
    [
        ([0.0, 1.0], [1.0, 1.0], 0.1),  # lower == upper
        ([0.0], [1.0], 0.0),  # sigma == 0
        ([0.0], [1.0], [0.1, 0.2]),  # sigma length
        ([0.0, 1.0], [1.0], 0.1),  # lengths differ
        ([np.nan], [1.0], 0.1),
    ],
)
def test_smoothed_box_validation(args):
    with pytest.raises(ConfigError):
        smoothed_box(*args)


def test_smoothed_box_wrong_dimension():
    with pytest.raises(ConfigError, match="box has 3"):
        smoothed_box(LOWER, UPPER, SIGMA)(jnp.zeros((2, 4)))


# ---------------------------------------------------------- inequality network

BOX = (-2.0, 6.0)  # log-space training box
ETA = 10.0
WIDTH = BOX[1] - BOX[0]


@pytest.fixture(scope="module")
def linear_net():
    return train_inequality_network(*BOX, eta=ETA)  # shipped defaults (~5-10 s on CPU)


def held_out(n=4000, seed=7):
    x = jax.random.uniform(jax.random.key(seed), (n, 2), minval=BOX[0], maxval=BOX[1])
    return x[:, 0], x[:, 1]


def test_linear_net_matches_target(linear_net):
    p, c = held_out()
    err = np.abs(np.asarray(linear_net(p, c) - inequality_target(p, c, ETA, "linear")))
    # Tolerance: mean |error| < 1.5% and, away from the kink (|p - c| > 10% of the
    # box), max |error| < 5% of the target range eta * width (= 80 here).
    assert err.mean() < 0.015 * ETA * WIDTH
    far = np.abs(np.asarray(p - c)) > 0.1 * WIDTH
    assert err[far].max() < 0.05 * ETA * WIDTH


def test_linear_net_gradient_points_into_feasible_region(linear_net):
    p, c = held_out()
    gp, gc = jax.vmap(jax.grad(linear_net, argnums=(0, 1)))(p, c)
    gp, gc = np.asarray(gp), np.asarray(gc)
    violated = np.asarray(c - p) > 0.1 * WIDTH
    assert np.all(gp[violated] > 0) and np.all(gc[violated] < 0)
    # slope of eq. 15 is +-eta there
    assert np.mean(gp[violated]) == pytest.approx(ETA, rel=0.1)
    assert np.mean(gc[violated]) == pytest.approx(-ETA, rel=0.1)
    satisfied = np.asarray(p - c) > 0.1 * WIDTH
    assert np.mean(np.abs(gp[satisfied])) < priors.FLAT_TOLERANCE * ETA
    assert np.mean(np.abs(gc[satisfied])) < priors.FLAT_TOLERANCE * ETA


def test_default_network_is_flat_where_the_inequality_holds(tmp_path):
    """Issue 11: the allowed side must be flat over the whole prior box as inference pads it
    (box of Kd [0.05, 10], widened by half its width on each side, as
    inference.nn_inequality_prior does). The bundled fit of format 2 had a mean slope of 8% of
    eta there and up to 25% beyond the band; the limits are priors.FLAT_*."""
    a, b = math.log(0.05), math.log(10.0)
    pad = 0.5 * (b - a)
    net = load_or_train_inequality_network(a - pad, b + pad, eta=ETA, cache_dir=tmp_path)
    assert net.loaded  # the bundled default
    x = jnp.linspace(a - pad, b + pad, 121)
    parent, child = (v.ravel() for v in jnp.meshgrid(x, x, indexing="ij"))
    gp, gc = jax.vmap(jax.grad(net, argnums=(0, 1)))(parent, child)
    slope = np.maximum(np.abs(np.asarray(gp)), np.abs(np.asarray(gc))) / ETA
    share = np.asarray(parent - child) / (2 * (b - a))  # of the trained (padded) range
    allowed = share > 0
    assert slope[allowed].mean() < priors.FLAT_MEAN_TOLERANCE
    assert slope[share > priors.FLAT_BAND].max() < priors.FLAT_TOLERANCE
    # and it still penalises violations with slope eta
    violated = share < -priors.FLAT_BAND
    assert np.mean(np.asarray(gc)[violated]) == pytest.approx(-ETA, rel=0.02)
    assert np.mean(np.asarray(gp)[violated]) == pytest.approx(ETA, rel=0.02)


def test_inequality_prior_chain_of_four_branches(linear_net):
    # theta = [logKp_0..3, logKd_0..3]; chain 0 -> 1 -> 2 -> 3 for both.
    pairs = [(0, 1), (1, 2), (2, 3), (4, 5), (5, 6), (6, 7)]
    logp = inequality_prior(linear_net, pairs)
    theta = jax.random.uniform(jax.random.key(3), (500, 8), minval=BOX[0], maxval=BOX[1])
    ref = sum(inequality_target(theta[:, i], theta[:, j], ETA) for i, j in pairs)
    got = logp(theta)
    assert got.shape == (500,)
    assert np.mean(np.abs(np.asarray(got - ref))) < 6 * 0.015 * ETA * WIDTH
    # exact sum of the network over the pairs
    net_sum = sum(linear_net(theta[:, i], theta[:, j]) for i, j in pairs)
    np.testing.assert_allclose(got, net_sum, rtol=1e-5, atol=1e-4)
    # gradient (autodiff) pushes a violating child down and its parent up
    bad = jnp.array([[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]]).at[0, 3].set(4.0)
    _, g = autodiff_value_and_grad(logp)(bad)
    assert g[0, 3] < -0.5 * ETA and g[0, 2] > 0.5 * ETA
    # satisfied chain: within the mean-error budget of 6 pairs, and far above
    # a chain with one violation by 4 log units (exact penalty -4 * eta)
    good = jnp.array([[4.0, 2.5, 1.0, -0.5, 4.0, 2.5, 1.0, -0.5]])
    assert abs(float(logp(good)[0])) < 6 * 0.015 * ETA * WIDTH
    assert float(logp(bad)[0]) < float(logp(good)[0]) - 0.8 * 4 * ETA
    with pytest.raises(ConfigError):
        logp(jnp.zeros((2, 5)))
    with pytest.raises(ConfigError):
        inequality_prior(linear_net, [(1, 1)])
    with pytest.raises(ConfigError):
        inequality_prior(linear_net, [(0, -1)])


def test_step_form_matches_target_away_from_the_step():
    net = train_inequality_network(*BOX, eta=ETA, form="step", steps=2000)
    p, c = held_out()
    err = np.abs(np.asarray(net(p, c) - inequality_target(p, c, ETA, "step")))
    far = np.abs(np.asarray(p - c)) > 0.1 * WIDTH
    # Tolerance: mean |error| < 5% of eta away from the step (the fit is smooth across it).
    assert err[far].mean() < 0.05 * ETA
    gp, gc = jax.vmap(jax.grad(net, argnums=(0, 1)))(p, c)
    near = np.abs(np.asarray(p - c)) < 0.02 * WIDTH
    assert np.mean(np.asarray(gp)[near]) > 0 and np.mean(np.asarray(gc)[near]) < 0


def test_training_is_seeded():
    a = train_inequality_network(0.0, 1.0, steps=30, n_samples=128, seed=3)
    b = train_inequality_network(0.0, 1.0, steps=30, n_samples=128, seed=3)
    c = train_inequality_network(0.0, 1.0, steps=30, n_samples=128, seed=4)
    jax.tree.map(np.testing.assert_array_equal, a.params, b.params)
    assert not np.array_equal(a.params["Dense_0"]["kernel"], c.params["Dense_0"]["kernel"])


@pytest.mark.parametrize(
    "kwargs",
    [
        {"box_low": 1.0, "box_high": 1.0},
        {"box_low": 0.0, "box_high": 1.0, "eta": 0.0},
        {"box_low": 0.0, "box_high": 1.0, "form": "quadratic"},
        {"box_low": 0.0, "box_high": 1.0, "hidden": 0},
        {"box_low": 0.0, "box_high": 1.0, "activation": "relu6"},
        {"box_low": 0.0, "box_high": 1.0, "sharpness": 0.0},
        {"box_low": 0.0, "box_high": 1.0, "grad_weight": -1.0},
        {"box_low": 0.0, "box_high": 1.0, "span": float("nan")},
    ],
)
def test_training_validation(kwargs):
    with pytest.raises(ConfigError):
        train_inequality_network(**kwargs)


def test_cache_second_call_loads(tmp_path, monkeypatch):
    settings = {
        "box_low": -1.0,
        "box_high": 2.0,
        "eta": 3.0,
        "steps": 20,
        "n_samples": 64,
        "hidden": 8,
    }
    first = load_or_train_inequality_network(**settings, cache_dir=tmp_path)
    assert not first.loaded and first.cache_path is not None
    files = list(tmp_path.iterdir())
    assert len(files) == 1 and files[0].suffix == ".msgpack"

    def boom(*a, **k):
        raise AssertionError("retrained although the weights are cached")

    monkeypatch.setattr(priors, "train_inequality_network", boom)
    second = load_or_train_inequality_network(**settings, cache_dir=tmp_path)
    assert second.loaded and second.settings == first.settings
    jax.tree.map(np.testing.assert_array_equal, first.params, second.params)
    x = jnp.linspace(-1, 2, 7)
    np.testing.assert_array_equal(first(x, x[::-1]), second(x, x[::-1]))

    # the box and eta only rescale the normalised fit: another box and eta load the same weights
    other = load_or_train_inequality_network(
        **{**settings, "eta": 4.0, "box_low": 0.0, "box_high": 6.0}, cache_dir=tmp_path
    )
    assert other.loaded
    # same normalised inputs (x -> 2x + 2 maps [-1, 2] onto [0, 6]), outputs scaled by eta * width
    np.testing.assert_allclose(
        other(2 * x + 2, 2 * x[::-1] + 2),
        first(x, x[::-1]) * (4.0 * 6.0) / (3.0 * 3.0),
        rtol=1e-5,
        atol=1e-6,
    )
    # a different fit setting is a different key -> trains (here: the patched trainer raises)
    with pytest.raises(AssertionError, match="retrained"):
        load_or_train_inequality_network(**{**settings, "hidden": 9}, cache_dir=tmp_path)

    # $TREEINFER_CACHE is the default folder
    monkeypatch.setenv("TREEINFER_CACHE", str(tmp_path))
    assert load_or_train_inequality_network(**settings).loaded


def test_corrupt_cache_is_retrained(tmp_path):
    settings = {"box_low": -1.0, "box_high": 2.0, "steps": 10, "n_samples": 32, "hidden": 4}
    first = load_or_train_inequality_network(**settings, cache_dir=tmp_path)
    with open(first.cache_path, "wb") as f:
        f.write(b"not msgpack")
    with pytest.warns(UserWarning, match="unusable"):
        again = load_or_train_inequality_network(**settings, cache_dir=tmp_path)
    assert not again.loaded
    assert load_or_train_inequality_network(**settings, cache_dir=tmp_path).loaded


def test_bundled_default_network_loads_and_matches_a_fresh_fit(linear_net, tmp_path, monkeypatch):
    """The package ships the default-settings fit (a fresh install skips training). It must be
    what training with the current code and defaults gives, or it is stale."""
    bundled = list(priors.BUNDLED_NETS.glob("inequality_net-*.msgpack"))
    assert len(bundled) == 1

    def boom(*a, **k):
        raise AssertionError("trained although the default fit is bundled")

    monkeypatch.setattr(priors, "train_inequality_network", boom)
    net = load_or_train_inequality_network(-2.0, 7.0, eta=10.0, cache_dir=tmp_path)  # empty cache
    assert net.loaded and Path(net.cache_path).parent == priors.BUNDLED_NETS
    monkeypatch.undo()
    # a fresh fit with the defaults: linear_net's weights, trained once for the module. Training
    # runs in normalised units, so the box and eta only rescale the same weights (as
    # test_cache_second_call_loads checks): linear_net is that fit read on the bundled box.
    fit = {k: v for k, v in linear_net.settings.items() if k not in ("box_low", "box_high", "eta")}
    assert fit == {k: v for k, v in net.settings.items() if k not in ("box_low", "box_high", "eta")}
    fresh = linear_net._replace(settings=net.settings)
    x = jnp.linspace(-2.0, 7.0, 41)
    parent, child = jnp.meshgrid(x, x)
    # same procedure and seed; float32 training on another machine may round differently
    np.testing.assert_allclose(net(parent, child), fresh(parent, child), atol=1e-3 * 10.0 * 9.0)


def test_network_files_load_and_run_without_flax_as_flax_does():
    """The cold-start path reads the bundled network with msgpack alone and applies it in plain
    jax.numpy (issue 15): both must equal flax's own restore and ``Module.apply``."""
    from flax import serialization

    from treeinfer.model.inequality_net import _mlp_apply, _model

    files = sorted(priors.BUNDLED_NETS.glob("inequality_net-*.msgpack"))
    assert files, "no bundled network"
    raw = files[0].read_bytes()
    ours, theirs = priors.read_net_file(raw), serialization.msgpack_restore(raw)
    assert ours.keys() == theirs.keys() and ours["settings_json"] == theirs["settings_json"]
    flat_ours, tree_ours = jax.tree.flatten(ours["params"])
    flat_theirs, tree_theirs = jax.tree.flatten(theirs["params"])
    assert tree_ours == tree_theirs
    for a, b in zip(flat_ours, flat_theirs):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    net = priors.load_or_train_inequality_network(0.0, 1.0)
    assert net.loaded
    u = jax.random.uniform(jax.random.key(0), (257, 2), minval=-1.2, maxval=1.2)
    flax_y = _model(net.settings).apply({"params": net.params}, u)
    np.testing.assert_allclose(
        _mlp_apply(net.params, net.settings, u), flax_y, rtol=1e-6, atol=1e-7
    )


def test_a_broken_network_file_extension_is_refused():
    import msgpack

    bad = msgpack.packb({"params": msgpack.ExtType(7, b"x")})
    with pytest.raises(ValueError, match="extension type 7"):
        priors.read_net_file(bad)


def test_smoothed_box_quantile_inverts_the_normalised_density():
    """The quantile function against the CDF integrated numerically from the density itself
    (``smoothed_box(normalized=True)``): CDF(quantile(u)) = u over both tails and the box."""
    lo, hi, s = np.array([1.0, -2.0]), np.array([3.0, 0.5]), np.array([0.4, 0.25])
    u = np.array([1e-4, 0.01, 0.05, 0.09, 0.2, 0.5, 0.8, 0.93, 0.99, 0.9999])
    q = priors.smoothed_box_quantile(np.tile(u[:, None], (1, 2)), lo, hi, s)
    for j in range(2):
        grid = np.linspace(lo[j] - 8 * s[j], hi[j] + 8 * s[j], 40001)
        dens = np.exp(np.asarray(smoothed_box(lo[j : j + 1], hi[j : j + 1], s[j : j + 1],
                                              normalized=True)(grid[:, None])))  # fmt: skip
        cdf = integrate.cumulative_trapezoid(dens, grid, initial=0.0)
        np.testing.assert_allclose(np.interp(q[:, j], grid, cdf), u, atol=2e-5)
    # the tails: a fifth of the mass (0.1 of the width) lies beyond the edges, split evenly
    a = 0.5 * (1 - 2.0 / (2.0 + math.sqrt(2 * math.pi) * 0.4))
    np.testing.assert_allclose(priors.smoothed_box_quantile([a], [1.0], [3.0], [0.4]), [1.0])
