"""Prior log-densities over the unconstrained parameter vector ``theta``.

Every prior here is a batched log-density term ``theta [P, D] -> log p0 [P]``
(see :mod:`treeinfer.model.gradients`), differentiable everywhere, so samplers get
exact autodiff gradients for it. In treeinfer ``theta`` holds ``log Kp`` and
``log Kd`` of the inferred joints (natural log of N*m/rad and N*m*s/rad); the
functions here are generic in ``D``.

* :func:`smoothed_box` -- the smoothed uniform "search box" prior (paper,
  "Smooth Box Prior", after GPyTorch's ``SmoothedBoxPrior``).
* :func:`train_inequality_network` / :func:`load_or_train_inequality_network`
  and :func:`inequality_prior` -- the neural-network inequality prior (paper
  eq. 12-16): a one-hidden-layer MLP regressor ``y'(theta_parent, theta_child)``
  approximating ``log p0``, which penalises a child parameter exceeding its parent's.
"""

from __future__ import annotations

import json
import math
import os
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError
from ..io.atomic import atomic_write_bytes

if TYPE_CHECKING:  # bound at run time by _net_names() (below)
    from .inequality_net import (  # noqa: F401 -- re-exported (see _NET_NAMES)
        DEFAULT_ALLOWED_WEIGHT,
        DEFAULT_GRAD_WEIGHT,
        DEFAULT_SHARPNESS,
        DEFAULT_SPAN,
        FLAT_BAND,
        FLAT_MEAN_TOLERANCE,
        FLAT_TOLERANCE,
        InequalityNet,
        _fit_key,
        _fit_settings,
        _settings_key,
        _training_settings,
        inequality_target,
        train_inequality_network,
    )

# Re-exported from :mod:`.inequality_net` (the old import path keeps working), imported on first
# use: it defines a flax module, and flax costs 0.15 s to import, which a run whose problem has
# no inequality prior (the smoothed box alone, the importance path's screening) need not pay.
_NET_NAMES = (
    "DEFAULT_ALLOWED_WEIGHT",
    "DEFAULT_GRAD_WEIGHT",
    "DEFAULT_SHARPNESS",
    "DEFAULT_SPAN",
    "FLAT_BAND",
    "FLAT_MEAN_TOLERANCE",
    "FLAT_TOLERANCE",
    "InequalityNet",
    "_fit_key",
    "_fit_settings",
    "_settings_key",
    "_training_settings",
    "inequality_target",
    "train_inequality_network",
)


def _net_names() -> None:
    """Bind :data:`_NET_NAMES` here (a name already set, e.g. by a test's monkeypatch, stays)."""
    from . import inequality_net

    for name in _NET_NAMES:
        globals().setdefault(name, getattr(inequality_net, name))


def __getattr__(name):
    if name in _NET_NAMES:
        _net_names()
        return globals()[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "smoothed_box_quantile",
    "InequalityNet",
    "default_cache_dir",
    "inequality_prior",
    "inequality_target",
    "load_or_train_inequality_network",
    "smoothed_box",
    "train_inequality_network",
]

# ----------------------------------------------------------------------------
# Smoothed box prior
# ----------------------------------------------------------------------------


def smoothed_box_quantile(u, lower, upper, sigma) -> np.ndarray:
    """The quantile function of :func:`smoothed_box` (normalised) per coordinate: ``u [..., D]``
    in (0, 1) to theta. The mixture of :func:`treeinfer.calibration.sample_smoothed_box` inverted
    piece by piece: the lower half-normal tail below ``a = (1 - p_box) / 2``, the
    uniform box between, the upper tail above ``1 - a``. Maps stratified uniforms (a Latin
    hypercube) to stratified prior points (the start pipeline's screen,
    :func:`treeinfer.inference.screen_points.prior_points`). The normal quantile is
    ``statistics.NormalDist`` (no SciPy import on the CLI's start path)."""
    from statistics import NormalDist

    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    s = np.broadcast_to(np.asarray(sigma, float), lo.shape)
    w = hi - lo
    p_box = w / (w + math.sqrt(2 * math.pi) * s)
    a = 0.5 * (1.0 - p_box)
    u = np.clip(np.asarray(u, float), 1e-12, 1.0 - 1e-12)
    inv = np.vectorize(NormalDist().inv_cdf, otypes=[float])
    # distance beyond an edge for tail mass m of the half-normal's a: 1 - m / (2 a) of N(0, 1)
    below = u < a
    above = u > 1.0 - a
    tail_u = np.where(below, u, 1.0 - u) / np.where(a > 0, 2.0 * a, 1.0)
    h = s * inv(np.clip(1.0 - tail_u, 0.5, 1.0 - 1e-12))
    inside = lo + (u - a) / p_box * w
    return np.where(below, lo - h, np.where(above, hi + h, inside))


def smoothed_box(
    lower: Sequence[float] | np.ndarray,
    upper: Sequence[float] | np.ndarray,
    sigma: float | Sequence[float] | np.ndarray,
    normalized: bool = False,
) -> Callable[[jax.Array], jax.Array]:
    """Smoothed box (soft uniform) prior on ``theta``.

    ``log p0(theta) = -sum_d dist_d(theta)^2 / (2 sigma_d^2)``
    ``[- sum_d log(upper_d - lower_d + sqrt(2 pi) sigma_d)]``

    with ``dist_d = max(|theta_d - c_d| - r_d, 0)`` the distance of coordinate
    ``d`` to the interval ``[lower_d, upper_d]`` (centre ``c``, half-width ``r``).
    The density is flat inside the box and has Gaussian tails of standard
    deviation ``sigma`` outside; value and gradient are continuous everywhere
    (the gradient ``-dist/sigma^2`` is 0 at the boundary), the second derivative
    jumps at the boundary.

    This is GPyTorch's ``SmoothedBoxPrior.log_prob`` (a uniform on the box mixed
    with two half-normal tails, normalised per coordinate). Its docstring (and
    the paper) write the exponent as ``d^2 / sqrt(2 sigma^2)``; the implementation,
    and this function, use ``d^2 / (2 sigma^2)``. With ``normalized=False``
    (default) the constant is dropped, which no sampler here needs;
    ``normalized=True`` adds it so the density integrates to 1.

    Args:
      lower, upper: box limits ``[D]`` in theta units (for treeinfer: natural log
        of Kp / Kd), ``lower < upper``.
      sigma: tail width, a float or ``[D]``, ``> 0``, same units.
      normalized: include the normalising constant.

    Returns:
      ``logdensity(theta [P, D]) -> [P]``.
    """
    lower = np.atleast_1d(np.asarray(lower, dtype=np.float64))
    upper = np.atleast_1d(np.asarray(upper, dtype=np.float64))
    if lower.ndim != 1 or upper.shape != lower.shape:
        raise ConfigError(
            f"smoothed_box: lower and upper must be vectors of the same length, "
            f"got shapes {lower.shape} and {upper.shape}"
        )
    try:
        sigma = np.broadcast_to(np.asarray(sigma, dtype=np.float64), lower.shape).copy()
    except ValueError:
        raise ConfigError(
            f"smoothed_box: sigma must be a float or have length {lower.size}, "
            f"got shape {np.shape(sigma)}"
        ) from None
    for name, arr in (("lower", lower), ("upper", upper), ("sigma", sigma)):
        if not np.all(np.isfinite(arr)):
            raise ConfigError(f"smoothed_box: {name} must be finite, got {arr.tolist()}")
    bad = np.nonzero(~(lower < upper))[0]
    if bad.size:
        d = int(bad[0])
        raise ConfigError(
            f"smoothed_box: need lower < upper in every coordinate; coordinate {d} has "
            f"lower={lower[d]} upper={upper[d]}"
        )
    bad = np.nonzero(~(sigma > 0))[0]
    if bad.size:
        d = int(bad[0])
        raise ConfigError(f"smoothed_box: sigma must be > 0; coordinate {d} has sigma={sigma[d]}")

    dim = lower.size
    centre = (lower + upper) / 2
    half_width = (upper - lower) / 2
    const = (
        float(np.sum(np.log(upper - lower + math.sqrt(2 * math.pi) * sigma))) if normalized else 0.0
    )

    def logdensity(theta: jax.Array) -> jax.Array:
        theta = jnp.asarray(theta)
        if theta.shape[-1] != dim:
            raise ConfigError(
                f"smoothed_box: theta has {theta.shape[-1]} coordinates, the box has {dim}"
            )
        dtype = jnp.result_type(theta, jnp.float32)
        c, r, s = (jnp.asarray(a, dtype) for a in (centre, half_width, sigma))
        dist = jnp.maximum(jnp.abs(theta - c) - r, 0.0)
        return -0.5 * jnp.sum(jnp.square(dist / s), axis=-1) - const

    return logdensity


# Fits shipped with the package, made by ``python -m treeinfer.model.priors`` (the default
# settings): read like cache files, so a fresh install skips training. Any other setting trains and
# caches.
BUNDLED_NETS = Path(__file__).resolve().parents[1] / "data"


def default_cache_dir() -> Path:
    """``$TREEINFER_CACHE`` if set, else ``~/.cache/treeinfer``."""
    env = os.environ.get("TREEINFER_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "treeinfer"


def load_or_train_inequality_network(
    box_low: float,
    box_high: float,
    eta: float = 10.0,
    form: str = "linear",
    hidden: int = 64,
    activation: str | None = None,
    n_samples: int = 8192,
    steps: int = 4000,
    learning_rate: float = 3e-2,
    seed: int = 0,
    cache_dir: str | os.PathLike | None = None,
    sharpness: float | None = None,
    grad_weight: float | None = None,
    allowed_weight: float | None = None,
    span: float | None = None,
) -> InequalityNet:
    """:func:`train_inequality_network` with a disk cache.

    The cache file is ``<cache_dir>/inequality_net-<hash>.msgpack`` where the
    hash covers every setting of the normalised fit (not the box or eta, which
    only rescale it), so any change to those retrains. Weights are
    written atomically (flax msgpack); an unreadable or mismatching file is
    retrained and overwritten (with a warning). ``cache_dir`` defaults to
    :func:`default_cache_dir`. The returned net has ``loaded=True`` when it
    came from the cache.
    """
    _net_names()
    settings = _training_settings(
        box_low,
        box_high,
        eta,
        form,
        hidden,
        activation,
        n_samples,
        steps,
        learning_rate,
        seed,
        sharpness,
        grad_weight,
        allowed_weight,
        span,
    )
    cache_dir = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
    path = cache_dir / f"inequality_net-{_fit_key(settings)}.msgpack"
    if not path.is_file() and (BUNDLED_NETS / path.name).is_file():
        path = BUNDLED_NETS / path.name  # the default fit ships with the package (3 s of training)
    if path.is_file():
        try:
            blob = read_net_file(path.read_bytes())
            stored = json.loads(blob["settings_json"])
            if stored != _fit_settings(settings):
                raise ValueError("stored settings differ from the requested ones")
            # device_put: jnp.asarray would run (and load) one small program per array shape
            params = jax.device_put(blob["params"])
            return InequalityNet(params, settings, float(blob["final_loss"]), str(path), True)
        except Exception as exc:  # noqa: BLE001 -- any unreadable/foreign file: retrain below
            warnings.warn(
                f"{path}: cached inequality network unusable ({exc}); retraining", stacklevel=2
            )
    from flax import serialization  # writing (after training) only

    # Look the trainer up by module name so tests can observe whether it ran.
    net = train_inequality_network(**{k: v for k, v in settings.items() if k != "format"})
    blob = {
        "settings_json": json.dumps(_fit_settings(settings), sort_keys=True),
        "params": jax.tree.map(np.asarray, serialization.to_state_dict(net.params)),
        "final_loss": net.final_loss,
    }
    atomic_write_bytes(path, serialization.msgpack_serialize(blob))
    return net._replace(cache_path=str(path))


def read_net_file(blob: bytes) -> dict:
    """A network file this package wrote (``flax.serialization.msgpack_serialize`` of a dict of
    arrays and plain values), read with msgpack alone.

    Why not ``flax.serialization.msgpack_restore``: importing flax costs ~0.3 s of every cold
    process (issue 15), and these files hold nothing but float arrays, which flax stores as
    msgpack extension type 1 = ``packb((shape, dtype name, raw buffer))``. Any other extension
    type is refused (the caller retrains). ``tests/test_priors.py`` checks this against flax on
    the bundled file."""
    import msgpack

    def ext_hook(code, data):
        if code != 1:
            raise ValueError(f"unexpected msgpack extension type {code} in a network file")
        shape, dtype_name, buffer = msgpack.unpackb(data, raw=True)
        return np.frombuffer(buffer, dtype=np.dtype(dtype_name.decode())).reshape(shape)

    return msgpack.unpackb(blob, ext_hook=ext_hook, raw=False, strict_map_key=False)


def inequality_prior(
    net: InequalityNet, pairs: Sequence[tuple[int, int]]
) -> Callable[[jax.Array], jax.Array]:
    """Inequality log-prior ``sum_{(i, j) in pairs} y'(theta_i, theta_j)`` (paper eq. 13/16).

    Args:
      net: a trained :class:`InequalityNet` (its box should cover the theta range).
      pairs: ``(parent_index, child_index)`` column pairs of theta, one per
        parent-child relation (e.g. Kp and Kd of every parent-child joint pair,
        any number of branches). Use one net per parameter kind when their
        ranges differ, and :func:`treeinfer.model.gradients.combine` the priors.

    Returns:
      ``logdensity(theta [P, D]) -> [P]`` (differentiable; use autodiff).
    """
    pairs = [tuple(p) for p in pairs]
    for k, p in enumerate(pairs):
        if (
            len(p) != 2
            or not all(isinstance(i, (int, np.integer)) and not isinstance(i, bool) for i in p)
            or min(p) < 0
        ):
            raise ConfigError(
                f"inequality_prior: pair {k} must be two non-negative indices, got {p}"
            )
        if p[0] == p[1]:
            raise ConfigError(f"inequality_prior: pair {k} relates index {p[0]} to itself")
    parent_idx = np.array([p[0] for p in pairs], dtype=np.int32)
    child_idx = np.array([p[1] for p in pairs], dtype=np.int32)
    max_idx = int(max(parent_idx.max(initial=-1), child_idx.max(initial=-1)))

    def logdensity(theta: jax.Array) -> jax.Array:
        theta = jnp.asarray(theta)
        if max_idx >= theta.shape[-1]:
            raise ConfigError(
                f"inequality_prior: pair index {max_idx} out of range for theta with "
                f"{theta.shape[-1]} coordinates"
            )
        if not pairs:
            return jnp.zeros(theta.shape[:-1], jnp.result_type(theta, jnp.float32))
        y = net(theta[..., parent_idx], theta[..., child_idx])  # [P, n_pairs]
        return jnp.sum(y, axis=-1)

    return logdensity


def _write_bundled_default() -> Path:
    """Train the inequality network with the default settings and store it in
    :data:`BUNDLED_NETS` (run by maintainers when the training code or defaults change)."""
    import tempfile

    from flax import serialization

    _net_names()

    with tempfile.TemporaryDirectory() as tmp:
        net = load_or_train_inequality_network(0.0, 1.0, cache_dir=tmp)
        if net.loaded:  # came from BUNDLED_NETS already: retrain to refresh it
            net = train_inequality_network(0.0, 1.0)
            blob = {
                "settings_json": json.dumps(_fit_settings(net.settings), sort_keys=True),
                "params": jax.tree.map(np.asarray, serialization.to_state_dict(net.params)),
                "final_loss": net.final_loss,
            }
            target = BUNDLED_NETS / f"inequality_net-{_fit_key(net.settings)}.msgpack"
            atomic_write_bytes(target, serialization.msgpack_serialize(blob))
            return target
        BUNDLED_NETS.mkdir(exist_ok=True)
        target = BUNDLED_NETS / Path(net.cache_path).name
        target.write_bytes(Path(net.cache_path).read_bytes())
        return target


if __name__ == "__main__":
    print(_write_bundled_default())
