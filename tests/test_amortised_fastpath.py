"""The amortised posterior in NumPy (treeinfer.amortised.fastpath) against flowjax's own
evaluation of the same weights: the summary, the draws of given base noise, the densities; and
the stored leaves' layout against flowjax's flattening (a release that reorders it fails here)."""

import numpy as np
import pytest

pytest.importorskip("flowjax")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from treeinfer.amortised import fastpath, network  # noqa: E402

DIM, N_FEATURES, LAYERS, WIDTH, EMBEDDING, N_SKIP = 5, 14, 3, 16, 4, 3
# the features' standardisation (network.build's norm): loc, scale per feature
NORM = (np.linspace(-2, 2, N_FEATURES), np.linspace(0.5, 3, N_FEATURES))


@pytest.fixture(scope="module")
def model():
    """A flow with every weight drawn at random (a fresh flow's last layers start near the
    identity, which would hide a wrong transformer parameterisation)."""
    m = network.build(jax.random.key(3), DIM, N_FEATURES, LAYERS, WIDTH, EMBEDDING, N_SKIP, NORM)
    rng = np.random.default_rng(0)
    vals = [
        v if v.dtype.kind in "bi" else (0.3 * rng.standard_normal(v.shape)).astype(v.dtype)
        for v in network.leaves(m)
    ]
    return network.with_leaves(m, vals, "test"), vals


def test_the_leaf_layout_is_flowjaxs_flattening(model):
    import equinox as eqx

    m, _ = model
    paths = jax.tree_util.tree_flatten_with_path(eqx.filter(m, eqx.is_array))[0]
    keys = [jax.tree_util.keystr(p) for p, _ in paths]
    names = fastpath.leaf_layout()
    assert len(keys) == len(names)
    for k, n in zip(keys, names):
        if n.startswith("phi") or n.startswith("rho"):
            i, p = n[3:].split(".")
            want = f".embed.{n[:3]}.layers[{i}].{'weight' if p == 'w' else 'bias'}"
            assert k == want
        elif n == "base.loc":
            assert k.endswith("base_dist.bijection.loc")
        elif n == "base.raw":
            assert k.endswith("base_dist.bijection.scale.args[0]")
        elif n.startswith("maf"):
            i, p = n[3:].split(".")
            tail = {"mask": "weight.args[0]", "w": "weight.args[1]", "b": "bias"}[p]
            assert k.endswith(f"masked_autoregressive_mlp.layers[{i}].{tail}")
        else:
            assert k.endswith({"perm": ".permutation[0]", "invperm": ".inverse_permutation[0]"}[n])


def test_numpy_summary_draws_and_densities_equal_flowjaxs(model):
    import paramax

    m, vals = model
    fe = fastpath.from_leaves(vals, DIM, N_FEATURES, LAYERS, WIDTH, EMBEDDING, N_SKIP, NORM)
    u = paramax.unwrap(m)
    feats = np.random.default_rng(1).standard_normal((3, N_FEATURES)).astype(np.float32)
    cond = np.asarray(u.embed(jnp.asarray(feats)))
    assert cond.shape == (EMBEDDING + N_SKIP,)  # the last features' means appended
    std = (feats - NORM[0]) / NORM[1]  # the skip connection sees the standardised features
    np.testing.assert_allclose(cond[-N_SKIP:], std[:, -N_SKIP:].mean(0), rtol=1e-5)
    np.testing.assert_allclose(fe.embed(feats), cond, rtol=1e-4, atol=1e-5)
    eps = np.random.default_rng(2).standard_normal((50, DIM)).astype(np.float32)
    x0 = np.asarray(jax.vmap(u.flow.base_dist.bijection.transform)(jnp.asarray(eps)))
    want = np.asarray(jax.vmap(lambda x: u.flow.bijection.transform(x, jnp.asarray(cond)))(x0))
    got = fe.transform(eps, cond)
    assert np.abs(want).max() > 1.0  # not the identity
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)
    lp_want = np.asarray(u.flow.log_prob(jnp.asarray(got), jnp.asarray(cond)))
    np.testing.assert_allclose(fe.log_prob(got, cond), lp_want, rtol=1e-4, atol=1e-3)
    # the draws' density is the flow's at them, whatever the seed
    z, lq = fe.sample_and_log_prob(np.random.default_rng(5), 20, feats)
    lq_want = np.asarray(u.flow.log_prob(jnp.asarray(z, jnp.float32), jnp.asarray(cond)))
    np.testing.assert_allclose(lq, lq_want, rtol=1e-4, atol=1e-3)


def test_weights_of_another_architecture_are_refused(model):
    from treeinfer.errors import ConfigError

    _, vals = model
    with pytest.raises(ConfigError, match="weight phi0.w has shape"):
        fastpath.from_leaves(vals, DIM, N_FEATURES + 1, LAYERS, WIDTH, EMBEDDING, N_SKIP)
    with pytest.raises(ConfigError, match="weight arrays"):
        fastpath.from_leaves(vals[:-1], DIM, N_FEATURES, LAYERS, WIDTH, EMBEDDING, N_SKIP)


def test_the_weights_file_reads_as_flax_writes_it(model):
    from flax.serialization import msgpack_restore, msgpack_serialize

    from treeinfer.amortised.estimator import read_weights

    _, vals = model
    blob = msgpack_serialize({str(i): a for i, a in enumerate(vals)})
    got, want = read_weights(blob), msgpack_restore(blob)
    assert sorted(got) == sorted(want) == sorted(str(i) for i in range(len(vals)))
    for k in want:
        assert got[k].dtype == want[k].dtype and got[k].shape == want[k].shape
        np.testing.assert_array_equal(got[k], want[k])


# ---- the posterior of a stored model: fast, nothing compiled, the same maths as flowjax's ----
FULL_MODEL = "experiments/results/amortised_full_two_branch/model"  # 6 layers, width 128


def test_a_loaded_models_first_posterior_compiles_nothing():
    """The issue's target (a new recording's posterior in < 100 ms on the 2-core CPU) rests on
    this: a loaded model's first posterior compiles no XLA program. Its time is a figure, not an
    assertion: ``benchmarks/amortised_latency.py`` prints it (about 7 CPU-ms for 1024 draws of
    the GPU-sized model, in the process's first call)."""
    from pathlib import Path

    from treeinfer.amortised import estimator
    from treeinfer.sim.compile_stats import compile_stats

    path = Path(__file__).resolve().parent.parent / FULL_MODEL
    am = estimator.load(path)
    assert am.model is None  # flowjax's modules are not built to answer
    lay = am.config.layout
    rng = np.random.default_rng(0)
    force = np.abs(rng.normal(3.0, 1.0, (lay.n_pulls, lay.n_steps)))
    disp = 0.01 * force + 1e-3 * rng.normal(size=force.shape)
    mark = compile_stats().mark()
    theta, log_q = am.draw(force, disp, 1024, seed=1)
    assert compile_stats().since(mark)["xla_compiles"] == 0
    assert theta.shape == (1024, len(am.labels)) and np.all(np.isfinite(log_q))


def test_a_stored_box_space_model_gives_flowjaxs_density():
    """A model from before the probit space and the dynamics summary (format 2 without those
    fields) still loads, and its NumPy density of draws is flowjax's (the old path)."""
    from pathlib import Path

    from treeinfer.amortised import estimator

    path = Path(__file__).resolve().parent.parent / "experiments/results/amortised_cpu_chain1/model"
    am = estimator.load(path)
    assert am.config.train.space == "box" and am.config.train.summary == "shapes"
    lay = am.config.layout
    rng = np.random.default_rng(2)
    force = np.abs(rng.normal(3.0, 1.0, (lay.n_pulls, lay.n_steps)))
    disp = 0.01 * force + 1e-3 * rng.normal(size=force.shape)
    theta, log_q = am.draw(force, disp, 64)
    feats = am.features(force, disp)
    want = np.asarray(
        network.log_density(am.network_model())(am.to_z(theta).astype(np.float32), feats)
    ) + am.log_jacobian(theta)
    np.testing.assert_allclose(log_q, want, rtol=1e-4, atol=2e-3)


# ---- the probit space ------------------------------------------------------------------------
def test_the_probit_space_makes_the_prior_a_standard_normal_and_inverts():
    from scipy import stats

    from treeinfer.amortised.simulations import draw_prior
    from treeinfer.amortised.space import ProbitSpace

    lo, hi = np.array([1.6, -3.0, -9.2]), np.array([6.2, 2.3, -5.3])
    tail = np.append(0.1 * (hi - lo)[:2], 0.0)  # the noise column has none (log-uniform)
    sp = ProbitSpace(lo, hi, tail)
    theta = draw_prior(np.random.default_rng(0), lo, hi, tail, 20000)
    u = sp.to_u(theta)
    for j in range(2):  # the smoothed box's draws are N(0, 1) in u
        assert stats.kstest(u[:, j], "norm").pvalue > 1e-3
    assert stats.kstest(np.random.default_rng(1).uniform(size=2000), "norm").pvalue < 1e-3
    np.testing.assert_allclose(sp.from_u(u), theta, atol=1e-9)
    far = np.array([[-5.0, -20.0, -30.0], [10.0, 4.0, 0.0]])  # far in the tails: still inverts
    assert np.all(np.isfinite(sp.to_u(far)))
    np.testing.assert_allclose(sp.from_u(sp.to_u(far)), far, atol=1e-8)
    # log |du/dtheta| against central differences, column by column
    h = 1e-6
    x = theta[:5]
    fd = sum(
        np.log(np.abs((sp.to_u(x + h * e)[:, j] - sp.to_u(x - h * e)[:, j]) / (2 * h)))
        for j, e in enumerate(np.eye(3))
    )
    np.testing.assert_allclose(sp.log_abs_det(x), fd, atol=1e-5)


# ---- the dynamics summaries ------------------------------------------------------------------
def test_the_dynamics_summaries_are_the_same_in_numpy_and_jax_and_measure_what_they_say():
    from treeinfer.amortised.simulations import bin_matrix, dynamics_features, features

    n, bins = 200, 50
    t = np.arange(n) * 0.01
    w = bin_matrix(n, bins)
    # a ramp-hold-release (released at 1.2 s) and a ramp that never lets go
    hold = np.clip(t / 0.5, 0, 1) * (t < 1.2)
    ramp = t / t[-1]
    force = np.stack([hold, ramp]) * 4.0
    ring = np.where(t > 1.2, 0.02 * np.exp(-4 * (t - 1.2)) * np.cos(25 * (t - 1.2)), 0.0)
    disp = 0.05 * force / 4.0 + np.stack([ring, np.zeros(n)])
    a = features(
        jnp.asarray(force, jnp.float32), jnp.asarray(disp, jnp.float32), w, 4.0, 0.05,
        summary="dynamics",
    )  # fmt: skip
    b = features(
        force.astype(np.float32), disp.astype(np.float32), w.astype(np.float32), 4.0, 0.05,
        xp=np, summary="dynamics",
    )  # fmt: skip
    np.testing.assert_allclose(np.asarray(a), b, atol=1e-5)
    d = dynamics_features((force / 4.0) @ w, (disp / 0.05) @ w, np)
    np.testing.assert_allclose(d[1, 1], 0.0, atol=1e-4)  # the hold's compliance: x = f exactly
    assert d[1, 5] == 0 and np.all(d[1, 2:5] == 0)  # no release: no ringing summaries
    assert d[0, 5] == 1 and d[0, 3] < -1  # released: the ringing decays
    assert 0.1 < d[0, 4] < 0.5  # 25 rad/s over 40 ms bins: a sign change every 3 bins


@pytest.mark.parametrize("space", ["box", "probit"])
def test_a_trained_models_draws_carry_their_density_in_theta_units(space):
    """Draws of a model trained in either space, their log q (NumPy, with the map's Jacobian)
    against flowjax's density of the same points in the flow's coordinates plus the Jacobian
    (and :meth:`Amortised.log_q`); the draws lie where the map sends them back."""
    import dataclasses

    from treeinfer.amortised import estimator
    from treeinfer.amortised.config import AmortiseConfig, PullLayout, TrainConfig
    from treeinfer.tree.generators import chain

    lay = PullLayout(n_pulls=2, duration=0.3, dt=0.01, peak_range=(1.0, 2.0))
    tr = TrainConfig(
        simulations=256, chunk=128, epochs=3, flow_layers=2, width=16, embedding=4,
        batch_size=64, sigma_x_range=(1e-3, 3e-3),
    )  # fmt: skip
    am = estimator.train(
        chain(1, lengths=0.7, radii=0.03, name="c1"),
        AmortiseConfig(lay, dataclasses.replace(tr, space=space)),
    )
    assert am.config.train.space == space and "feature_norm" in am.meta
    rng = np.random.default_rng(4)
    force = np.abs(rng.normal(1.5, 0.3, (lay.n_pulls, lay.n_steps)))
    disp = 0.01 * force + 2e-3 * rng.normal(size=force.shape)
    theta, log_q = am.draw(force, disp, 200, seed=3)
    feats = am.features(force, disp)
    z = am.to_z(theta)
    np.testing.assert_allclose(am.from_z(z), theta, atol=1e-6)
    want = np.asarray(
        network.log_density(am.network_model())(z.astype(np.float32), feats)
    ) + am.log_jacobian(theta)
    np.testing.assert_allclose(log_q, want, rtol=1e-4, atol=2e-3)
    np.testing.assert_allclose(am.log_q(theta, feats), log_q, rtol=1e-6, atol=1e-6)


def test_the_null_gap_is_the_binomial_spread_of_a_calibrated_posterior():
    """The largest coverage gap an exact posterior shows: for one column and the 50% level
    alone it is |Binomial(n, 1/2) / n - 1/2|, whose median is 0.6745 sd (sd = 0.5 / sqrt(n));
    over 5 columns x 4 levels it is larger, and it shrinks as 1 / sqrt(n)."""
    from treeinfer.amortised.calibration import null_max_gap

    one = null_max_gap(2000, 1, levels=(0.5,), reps=1000)
    assert abs(one["median"] - 0.6745 * 0.5 / np.sqrt(2000)) < 0.002
    small, large = null_max_gap(500, 5, reps=300), null_max_gap(5000, 5, reps=300)
    assert small["median"] > 0.03 > one["median"]
    assert 2.5 < small["median"] / large["median"] < 3.8  # sqrt(10) = 3.16
