"""The neural posterior estimator: a learned summary of the recordings (an MLP over each pull's
features, averaged over the pulls, so their order does not matter, then an MLP) conditioning a
masked autoregressive flow (flowjax, affine transformers) over the standardised parameters.

Why flowjax (an optional dependency, ``pip install treeinfer[amortise]``, imported only here and
only when a model is built): a maintained JAX library of conditional flows with a training loop
(early stopping on a held-out share); distrax would pull in TensorFlow Probability. Why affine
transformers rather than splines: the posteriors are often far narrower than the prior (a
thousandth of its width in log Kp for a few pulls at 1 mm noise), which an affine scale reaches
and a spline on a fixed interval does not.

The weights are stored with flax's msgpack (the array leaves in order, :func:`leaves` /
:func:`with_leaves`); the architecture is rebuilt from the recorded settings."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..errors import ConfigError

INSTALL_HINT = "the amortised posterior needs flowjax: pip install 'treeinfer[amortise]'"


def _flowjax():
    """``(equinox, flowjax.flows, flowjax.distributions)``, or ConfigError naming the extra."""
    try:
        import equinox as eqx
        import flowjax.distributions as fd
        import flowjax.flows as ff
    except ImportError as e:
        raise ConfigError(f"{INSTALL_HINT} ({e})") from None
    return eqx, ff, fd


def build(
    key,
    dim: int,
    n_features: int,
    layers: int,
    width: int,
    embedding: int,
    n_skip: int = 0,
    norm=None,
):
    """A fresh (untrained) estimator: ``Estimator(embed, flow)`` with ``embed(feats [..., B, F])
    -> [..., embedding + n_skip]`` and ``flow`` a conditional flow over ``dim`` standardised
    columns. ``n_skip``: the last ``n_skip`` features' means over the pulls are appended to the
    learned summary (:func:`skip_count`). ``norm``: ``(loc, scale)`` per feature, the training
    set's, subtracted and divided before anything else (None: the features as they are, the
    models before session 13): the features' logs span from about -9 to 1 and the networks
    learn faster on standardised inputs, the skip connection's above all.

    Built op by op: each small initialisation op compiles on its own the first time (10 s on a
    2-core CPU; the persistent compile cache keeps them). It cannot be one compiled program:
    flowjax keeps a closure over an intermediate array of its conditioner (a leaked tracer
    under ``jit`` or ``eval_shape``)."""
    return _build(key, dim, n_features, layers, width, embedding, n_skip, norm)


def skip_count(summary: str) -> int:
    """The features whose means over the pulls go to the flow as they are, beside the learned
    summary: for summary "dynamics", its hand-made summaries and the four amplitudes and noise
    estimates (:func:`treeinfer.amortised.simulations.features`). Why: the posterior of
    ``log sigma_x`` is about 1% of its prior's width and sits at the recording's own noise
    estimate; through the deep-sets MLP the flow found it only roughly and widened the rest
    (coverage 54-56% at 50% at the CPU size). None for "shapes" (the models before)."""
    from .simulations import N_DYNAMICS

    return N_DYNAMICS + 4 if summary == "dynamics" else 0


def _build(key, dim, n_features, layers, width, embedding, n_skip=0, norm=None):
    import jax

    eqx, ff, fd = _flowjax()
    import jax.numpy as jnp

    class Summary(eqx.Module):
        """Deep-sets summary: ``rho(mean_b phi(x_b))`` over the pulls ``b``."""

        phi: eqx.nn.MLP
        rho: eqx.nn.MLP
        n_skip: int = eqx.field(static=True, default=0)
        # tuples (hashable: static fields), not arrays: not weights, and not stored leaves
        norm_loc: tuple = eqx.field(static=True, default=())
        norm_scale: tuple = eqx.field(static=True, default=())

        def __call__(self, feats):
            if self.norm_loc:
                loc = jnp.asarray(self.norm_loc, feats.dtype)
                feats = (feats - loc) / jnp.asarray(self.norm_scale, feats.dtype)
            h = jax.vmap(self.phi)(feats.reshape(-1, feats.shape[-1]))
            h = h.reshape(*feats.shape[:-1], -1).mean(axis=-2)
            flat = h.reshape(-1, h.shape[-1])
            out = jax.vmap(self.rho)(flat).reshape(*h.shape[:-1], -1)
            if self.n_skip:
                out = jnp.concatenate([out, feats[..., -self.n_skip :].mean(axis=-2)], axis=-1)
            return out

    class Estimator(eqx.Module):
        embed: Summary
        flow: object

        def log_prob(self, z, feats):
            return self.flow.log_prob(z, self.embed(feats))

    k1, k2, k3 = jax.random.split(key, 3)
    phi = eqx.nn.MLP(n_features, width, width, 2, activation=jax.nn.gelu, key=k1)
    rho = eqx.nn.MLP(width, embedding, width, 1, activation=jax.nn.gelu, key=k2)
    flow = ff.masked_autoregressive_flow(
        k3,
        base_dist=fd.Normal(jnp.zeros(dim)),
        cond_dim=embedding + n_skip,
        flow_layers=layers,
        nn_width=width,
        # True (flowjax's default): the density is one pass per layer, what training takes
        # millions of; sampling inverts autoregressively, D passes per layer, still
        # milliseconds for the D <= ~10 columns of a tree (benchmarks/amortised_latency.py)
        invert=True,
    )
    loc, scale = ((), ()) if norm is None else (tuple(map(float, a)) for a in norm)
    return Estimator(Summary(phi, rho, n_skip, loc, scale), flow)


def _params(model):
    import paramax

    eqx, _, _ = _flowjax()
    return eqx.partition(
        model, eqx.is_inexact_array, is_leaf=lambda x: isinstance(x, paramax.NonTrainable)
    )


def leaves(model) -> list[np.ndarray]:
    """The model's array leaves, in order (what is stored): the weights and the integer ones
    too (the flow's random permutations between layers, drawn when it is built)."""
    import jax

    eqx, _, _ = _flowjax()
    arrays = eqx.filter(model, eqx.is_array)
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(arrays)]


def with_leaves(model, values, where: str):
    """``model`` with its array leaves replaced by ``values`` (shapes checked: a file from
    another architecture is refused, naming ``where``)."""
    import jax
    import jax.numpy as jnp

    eqx, _, _ = _flowjax()
    arrays, static = eqx.partition(model, eqx.is_array)
    flat, treedef = jax.tree_util.tree_flatten(arrays)
    if len(flat) != len(values):
        raise ConfigError(f"{where}: {len(values)} weight arrays, the architecture has {len(flat)}")
    for i, (a, v) in enumerate(zip(flat, values)):
        if tuple(a.shape) != tuple(np.shape(v)):
            raise ConfigError(
                f"{where}: weight array {i} has shape {tuple(np.shape(v))}, the architecture "
                f"expects {tuple(a.shape)}"
            )
    new = [jnp.asarray(v, a.dtype) for a, v in zip(flat, values)]
    new = jax.tree_util.tree_unflatten(treedef, new)
    return eqx.combine(new, static)


def fit(
    model,
    z,
    feats,
    key,
    epochs: int,
    batch_size: int,
    learning_rate: float,
    patience: int,
    progress: bool = False,
    deadline: float | None = None,
    log: Callable[[str], None] | None = None,
):
    """``(model, losses)``: maximum likelihood of ``z [N, D]`` given ``feats [N, B, F]``, Adam
    with a cosine decay, a tenth held out, the best epoch's weights kept, early stop after
    ``patience`` epochs without a better held-out loss; the loss the estimator's own negative
    log density. ``deadline`` (a :func:`time.perf_counter` value; None: none): no epoch but the
    first starts after it (``losses["stopped_at_deadline"]``); with ``progress``, ``log`` gets
    a line after the first epoch and then every 10 s.

    flowjax's :func:`~flowjax.train.fit_to_data` loop, step for step (its ``step``,
    ``train_val_split``, ``get_batches``, ``count_fruitless`` and the same keys: the same
    weights, ``tests/test_amortised.py``), written out here because it has no time limit and
    no progress but a tqdm bar: a GPU command has 10 minutes, and a run killed at them loses
    the model."""
    import time

    import jax.numpy as jnp
    import jax.random as jr
    import optax
    import paramax
    from flowjax.train.train_utils import count_fruitless, get_batches, step, train_val_split

    eqx, _, _ = _flowjax()

    def loss(params, static, z, feats, key=None):
        m = paramax.unwrap(eqx.combine(params, static))
        return -m.log_prob(z, feats).mean()

    n_train = max(1, int(0.9 * len(z)) // batch_size)
    batch_size = min(batch_size, max(1, int(0.1 * len(z))))
    optimizer = optax.adam(optax.cosine_decay_schedule(learning_rate, epochs * n_train, alpha=0.05))
    params, static = eqx.partition(
        model, eqx.is_inexact_array, is_leaf=lambda leaf: isinstance(leaf, paramax.NonTrainable)
    )
    best, opt_state = params, optimizer.init(params)
    key, subkey = jr.split(key)
    train_data, val_data = train_val_split(subkey, (jnp.asarray(z), jnp.asarray(feats)), 0.1)
    losses = {"train": [], "val": []}
    val_loss = eqx.filter_jit(loss)
    t0 = t_log = time.perf_counter()
    stopped = False
    for epoch in range(epochs):
        if deadline is not None and epoch and time.perf_counter() > deadline:
            stopped = True
            break
        key, *subkeys = jr.split(key, 3)
        train_data = [jr.permutation(subkeys[0], a) for a in train_data]
        val_data = [jr.permutation(subkeys[1], a) for a in val_data]
        batch_losses = []
        for batch in zip(*get_batches(train_data, batch_size), strict=True):
            key, subkey = jr.split(key)
            params, opt_state, loss_i = step(
                params, static, *batch, optimizer=optimizer, opt_state=opt_state,
                loss_fn=loss, key=subkey,
            )  # fmt: skip
            batch_losses.append(loss_i)
        losses["train"].append((sum(batch_losses) / len(batch_losses)).item())
        batch_losses = []
        for batch in zip(*get_batches(val_data, batch_size), strict=True):
            key, subkey = jr.split(key)
            batch_losses.append(val_loss(params, static, *batch, key=subkey))
        losses["val"].append((sum(batch_losses) / len(batch_losses)).item())
        if progress and log is not None and (epoch == 0 or time.perf_counter() - t_log > 10.0):
            t_log = time.perf_counter()
            log(
                f"epoch {epoch + 1}/{epochs}: loss {losses['train'][-1]:.4f}, held-out "
                f"{losses['val'][-1]:.4f} ({t_log - t0:.0f} s)"
            )
        if losses["val"][-1] == min(losses["val"]):
            best = params
        elif count_fruitless(losses["val"]) > patience:
            break
    losses["stopped_at_deadline"] = stopped
    return eqx.combine(best, static), losses


def sampler(model, n: int):
    """A jitted ``(key, feats [B, F]) -> (z [n, D], log q(z) [n])`` for one recording."""
    import paramax

    eqx, _, _ = _flowjax()
    model = paramax.unwrap(model)

    @eqx.filter_jit
    def draw(m, key, feats):
        return m.flow.sample_and_log_prob(key, (n,), condition=m.embed(feats))

    return lambda key, f: draw(model, key, f)


def log_density(model):
    """A jitted ``(z [M, D], feats [B, F]) -> log q(z) [M]`` (the flow's density at given
    points, e.g. the truth of a held-out data set)."""
    import paramax

    eqx, _, _ = _flowjax()
    model = paramax.unwrap(model)

    @eqx.filter_jit
    def dens(m, z, feats):
        return m.flow.log_prob(z, m.embed(feats))

    return lambda z, f: dens(model, z, f)
