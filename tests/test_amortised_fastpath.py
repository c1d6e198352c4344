"""The amortised posterior in NumPy (treeinfer.amortised.fastpath) against flowjax's own
evaluation of the same weights: the summary, the draws of given base noise, the densities; and
the stored leaves' layout against flowjax's flattening (a release that reorders it fails here)."""

import numpy as np
import pytest

pytest.importorskip("flowjax")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from treeinfer.amortised import fastpath, network  # noqa: E402

DIM, N_FEATURES, LAYERS, WIDTH, EMBEDDING = 5, 14, 3, 16, 4


@pytest.fixture(scope="module")
def model():
    """A flow with every weight drawn at random (a fresh flow's last layers start near the
    identity, which would hide a wrong transformer parameterisation)."""
    m = network.build(jax.random.key(3), DIM, N_FEATURES, LAYERS, WIDTH, EMBEDDING)
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
    fe = fastpath.from_leaves(vals, DIM, N_FEATURES, LAYERS, WIDTH, EMBEDDING)
    u = paramax.unwrap(m)
    feats = np.random.default_rng(1).standard_normal((3, N_FEATURES)).astype(np.float32)
    cond = np.asarray(u.embed(jnp.asarray(feats)))
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
        fastpath.from_leaves(vals, DIM, N_FEATURES + 1, LAYERS, WIDTH, EMBEDDING)
    with pytest.raises(ConfigError, match="weight arrays"):
        fastpath.from_leaves(vals[:-1], DIM, N_FEATURES, LAYERS, WIDTH, EMBEDDING)


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
