"""The trained estimator evaluated in NumPy: a new recording's posterior (summary, flow draws and
their log densities) with no JAX program to trace, compile or load.

Why not flowjax's own sampler (:func:`treeinfer.amortised.network.sampler`), which training and
calibration keep using: in a fresh ``treeinfer infer --amortised`` process it costs seconds
before the first answer on the 2-core CPU (building the flow's modules op by op to receive the
weights, 3-4 s; tracing and compiling, or loading from the persistent compile cache, the
sampler and the features, 0.5-1.2 s), against the issue's 100 ms; a serialised program
(``jax.export``) still took 0.5 s to load and lower. The network is small (a few MLPs and
``flow_layers`` masked autoregressive layers over D <= ~10 columns): NumPy evaluates it in
milliseconds, and the condition's contribution to each masked layer's first matrix product is
one vector per recording, computed once.

The arrays are read from the stored leaves in flowjax's flattening order (:func:`from_leaves`,
the layout :func:`leaf_layout` spells out); ``tests/test_amortised_fastpath.py`` checks the
layout against a built flowjax model and the draws and densities against flowjax's, so a
flowjax release that reorders its leaves fails there, not in a user's run."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError

# flowjax's default transformer: an affine whose scale is softplus(raw + init) + MIN_SCALE,
# raw the network's output and init such that a zero output is the identity
MIN_SCALE = 1e-2
_RAW_INIT = math.log(math.expm1(1 - MIN_SCALE))  # flowjax's inv_softplus(1 - MIN_SCALE)
_LOG_2PI = math.log(2 * math.pi)


def _softplus(x):
    return np.logaddexp(x, 0.0)


def _gelu(x):
    # jax.nn.gelu's default (approximate=True): the tanh form
    return 0.5 * x * (1.0 + np.tanh(math.sqrt(2 / math.pi) * (x + 0.044715 * x**3)))


def _mlp(layers, x, act):
    """``eqx.nn.MLP`` with ``layers`` [(W [out, in], b [out])]: act between layers, none at the
    end."""
    for i, (w, b) in enumerate(layers):
        x = x @ w.T + b
        if i < len(layers) - 1:
            x = act(x)
    return x


def leaf_layout(phi_layers: int = 3, rho_layers: int = 2) -> list[str]:
    """The names of the stored leaves in order (:func:`treeinfer.amortised.network.leaves`):
    equinox flattens the summary's MLPs (weight, bias per layer), then the flow's base (loc,
    raw scale), then the masked autoregressive layers stacked over the flow's layers (per
    linear layer: mask, weight, bias) and the permutations between them."""
    names = [f"phi{i}.{p}" for i in range(phi_layers) for p in ("w", "b")]
    names += [f"rho{i}.{p}" for i in range(rho_layers) for p in ("w", "b")]
    names += ["base.loc", "base.raw"]
    names += [f"maf{i}.{p}" for i in range(2) for p in ("mask", "w", "b")]
    return names + ["perm", "invperm"]


@dataclass
class FastEstimator:
    """The arrays of a trained estimator (float32) and the maths of its summary and flow."""

    phi: list
    rho: list
    base_loc: np.ndarray  # [D]
    base_scale: np.ndarray  # [D]
    # per flow layer, the masked weights split and transposed for the products above:
    # ((W0x^T [D, H], W0c [H, C], b0 [H]), ((W1loc^T, W1raw^T) [H, D] each, (b1loc, b1raw)))
    maf: list
    perm: np.ndarray  # [L, D]
    invperm: np.ndarray  # [L, D]
    n_skip: int = 0  # the last features' means appended to the summary (network.skip_count)
    norm: tuple | None = None  # (loc [F], scale [F]) of the features, or None (network.build)

    @property
    def dim(self) -> int:
        return self.base_loc.size

    # ---- the summary ---------------------------------------------------------------------------
    def embed(self, feats) -> np.ndarray:
        """[C] the condition of one recording's features [B, F] (the deep-sets summary)."""
        feats = np.asarray(feats, np.float32)
        if self.norm is not None:
            feats = (feats - self.norm[0]) / self.norm[1]
        out = _mlp(self.rho, _mlp(self.phi, feats, _gelu).mean(axis=0), _gelu)
        if self.n_skip:
            out = np.concatenate([out, feats[:, -self.n_skip :].mean(axis=0)])
        return out

    # ---- the flow -----------------------------------------------------------------------------
    def _layer_bias(self, cond):
        """Per flow layer, the first linear layer's bias plus the condition's share of its
        product (the condition is the same for every draw of a recording)."""
        return [c @ cond + b0 for (_, c, b0), _ in self.maf]

    def _params(self, layer: int, x, bias0, cols=slice(None)):
        """``(loc, scale)`` [n, D] (or of the columns ``cols``) of the affine transformer of
        flow layer ``layer`` at ``x``."""
        (wx, _, _), (w1t, b1) = self.maf[layer]
        h = np.maximum(x @ wx + bias0, 0.0)  # flowjax's relu
        loc = h @ w1t[0][:, cols] + b1[0][cols]
        raw = h @ w1t[1][:, cols] + b1[1][cols]
        return loc, _softplus(raw + _RAW_INIT) + MIN_SCALE

    def log_prob(self, z, cond) -> np.ndarray:
        """[n] log q(z [n, D] | cond): each masked layer forward, one pass (flowjax's
        ``Invert(Scan)``: its inverse is the layers' forward maps in order, each followed by
        its permutation), then the base Normal."""
        x = np.asarray(z, np.float32)
        bias = self._layer_bias(np.asarray(cond, np.float32))
        log_det = np.zeros(len(x))
        for layer in range(len(self.maf)):
            loc, scale = self._params(layer, x, bias[layer])
            x = (x * scale + loc)[:, self.perm[layer]]
            log_det += np.log(scale).sum(axis=1)
        e = ((x - self.base_loc) / self.base_scale).astype(float)
        base = -0.5 * (e**2 + _LOG_2PI).sum(axis=1) - np.log(self.base_scale).sum()
        return base + log_det

    def sample(self, rng: np.random.Generator, n: int, cond) -> np.ndarray:
        """[n, D] draws of the flow given ``cond``."""
        return self.transform(rng.standard_normal((n, self.dim), dtype=np.float32), cond)

    def transform(self, eps, cond) -> np.ndarray:
        """[n, D] the flow's draws of standard normal ``eps`` [n, D]: the base Normal's affine,
        then the layers in reverse order, each its inverse permutation and the autoregressive
        inverse (column ``r`` from the network's output at the columns before it, D passes per
        layer, each computing column ``r``'s parameters only; flowjax's ``inv_scan_fn``)."""
        bias = self._layer_bias(np.asarray(cond, np.float32))
        y = self.base_loc + self.base_scale * np.asarray(eps, np.float32)
        for layer in reversed(range(len(self.maf))):
            y = y[:, self.invperm[layer]]
            x = y.copy()
            for r in range(self.dim):
                loc, scale = self._params(layer, x, bias[layer], slice(r, r + 1))
                x[:, r] = (y[:, r] - loc[:, 0]) / scale[:, 0]
            y = x
        return y

    def sample_and_log_prob(self, rng, n: int, feats):
        cond = self.embed(feats)
        z = self.sample(rng, n, cond)
        return z, self.log_prob(z, cond)


def from_leaves(
    values,
    dim: int,
    n_features: int,
    layers: int,
    width: int,
    embedding: int,
    n_skip: int = 0,
    norm=None,
):
    """A :class:`FastEstimator` from the stored leaves (:func:`leaf_layout`'s order), shapes
    checked against the recorded architecture (ConfigError: a file of another one)."""
    names = leaf_layout()
    if len(values) != len(names):
        raise ConfigError(f"amortised model: {len(values)} weight arrays, expected {len(names)}")
    a = dict(zip(names, (np.asarray(v) for v in values)))
    want = {
        "phi0.w": (width, n_features),
        "rho1.w": (embedding, width),
        "base.loc": (dim,),
        "maf0.w": (layers, width, dim + embedding + n_skip),
        "maf1.w": (layers, 2 * dim, width),
        "perm": (layers, dim),
    }
    for k, shape in want.items():
        if a[k].shape != shape:
            raise ConfigError(
                f"amortised model: weight {k} has shape {a[k].shape}, the recorded "
                f"architecture expects {shape}"
            )
    # float32, as the network was trained: half the memory traffic of float64, which on the
    # 2-core CPU is what the autoregressive passes spend their time on
    f = lambda k: a[k].astype(np.float32)  # noqa: E731
    phi = [(f(f"phi{i}.w"), f(f"phi{i}.b")) for i in range(3)]
    rho = [(f(f"rho{i}.w"), f(f"rho{i}.b")) for i in range(2)]
    # the masks applied once (paramax.Parameterize(jnp.where, mask, weight, 0))
    w0 = np.where(a["maf0.mask"], f("maf0.w"), 0.0)
    w1 = np.where(a["maf1.mask"], f("maf1.w"), 0.0)
    b1 = f("maf1.b")
    maf = [
        (
            (np.ascontiguousarray(w0[i][:, :dim].T), np.ascontiguousarray(w0[i][:, dim:]),
             f("maf0.b")[i]),
            # the network's outputs are (loc, raw scale) per column, interleaved
            ((np.ascontiguousarray(w1[i][0::2].T), np.ascontiguousarray(w1[i][1::2].T)),
             (b1[i][0::2], b1[i][1::2])),
        )
        for i in range(layers)
    ]  # fmt: skip
    return FastEstimator(
        phi,
        rho,
        f("base.loc"),
        _softplus(f("base.raw")),
        maf,
        a["perm"].astype(int),
        a["invperm"].astype(int),
        n_skip,
        None if norm is None else tuple(np.asarray(v, np.float32) for v in norm),
    )
