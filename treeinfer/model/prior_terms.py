"""The prior terms of an inference problem: the smoothed box over the inferred gains and the
learned parent-stiffer-than-child inequality prior (NNSVGD's). Re-exported by
:mod:`treeinfer.inference.problem`."""

from __future__ import annotations

from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError
from ..tree.description import Tree
from .gradients import combine
from .priors import inequality_prior, load_or_train_inequality_network, smoothed_box

DEFAULT_ETA = 10.0  # nats per unit of log-gain violation (paper: eta >> 0)
DEFAULT_PRIOR_SIGMA = 0.1  # tail width of the smoothed box, as a share of each log-box width


def box_prior(
    tree: Tree, prior_sigma: float = DEFAULT_PRIOR_SIGMA, prior_space: str = "log", layout=None
):
    """Smoothed box over the inferred joints' gains as a theta-space log-density (``layout``:
    a :class:`treeinfer.inference.static.ParameterLayout`, for stiffness only)."""
    if layout is not None and hasattr(layout, "log_prior"):  # a tied layout's own prior
        return layout.log_prior(prior_sigma, prior_space)
    lo, hi = tree.bounds_array()
    if layout is not None:
        lo, hi = np.exp(layout.lower), np.exp(layout.upper)
    if prior_space == "log":
        llo, lhi = np.log(lo), np.log(hi)
        return smoothed_box(llo, lhi, prior_sigma * (lhi - llo))
    if prior_space == "linear":
        box = smoothed_box(lo, hi, prior_sigma * (hi - lo))
        # density of K = exp(theta) expressed in theta: p(theta) = p_K(exp theta) * |dK/dtheta|
        return lambda theta: box(jnp.exp(theta)) + jnp.sum(theta, axis=-1)
    raise ConfigError(f"prior_space: expected 'log' or 'linear', got {prior_space!r}")


def nn_inequality_prior(
    tree: Tree,
    eta: float = DEFAULT_ETA,
    form: str = "linear",
    seed: int = 0,
    cache_dir=None,
    kinds: Sequence[str] = ("Kp", "Kd"),
):
    """The learned inequality prior on every inferred parent-child pair, for Kp and for Kd.

    One network per gain kind (their log ranges differ), trained over that kind's log box
    (widened by the tails) and cached on disk."""
    pairs = tree.inferred_pairs()
    if not pairs:
        return None
    r = tree.n_inferred
    lo, hi = np.log(tree.bounds_array()[0]), np.log(tree.bounds_array()[1])
    terms = []
    for kind, cols in (("Kp", slice(0, r)), ("Kd", slice(r, 2 * r))):
        if kind not in kinds:
            continue
        a, b = float(lo[cols].min()), float(hi[cols].max())
        pad = 0.5 * (b - a)  # cover the smoothed box's tails too
        net = load_or_train_inequality_network(
            a - pad, b + pad, eta=eta, form=form, seed=seed, cache_dir=cache_dir
        )
        off = 0 if kind == "Kp" else r
        terms.append(inequality_prior(net, [(p + off, c + off) for p, c in pairs]))
    return combine(*terms)
