"""The force-noise term with its Jacobian taken at SEVERAL references: one per lobe of the
posterior (:mod:`treeinfer.model.force_noise`'s ``C = sigma_F^2 J J^T`` and its bias correction
are first order about ONE reference ``theta_ref``).

Why: the posterior of the standard problem can have two lobes far apart in the log gains (a
parent's and a child's stiffness trading off; SBC data set 90 of
``experiments/results/sbc_default_s15_lm/``: ``[4.24, 4.26, 7.11, ...]`` and ``[3.43, 5.62,
5.67, ...]``). Linearised in either lobe, the term misjudges the OTHER one: with ``J`` taken in
the truth's lobe the other lobe scored 3.6-3.9 nats higher, with ``J`` taken in the other lobe
the truth's scored 2.2 higher, while each lobe under its own linearisation scores about the same
(-4217.56 / -4217.36). So whichever lobe the reference sits in, the posterior put its mass in the
other one, and 95% intervals missed the truth by many standard deviations.

What this module does: with references ``r_1..r_K`` (each a self-consistent MAP: the mode of
the term linearised at itself, :func:`treeinfer.inference.start_pipeline.force_noise_reference`),
the log-likelihood at ``theta`` is the blend

    log p(theta) = sum_k w_k(theta) log p_k(theta),   w = softmax_k(-|theta_g - r_k|^2 / (2 h^2))

of the term linearised at each reference, ``h`` = :data:`LOCAL_SCALE` log units: near a lobe's
reference (where its first-order term is accurate) its own linearisation holds, and the weights
switch smoothly (so the LM's autodiff curvature stays finite) in the valley between lobes, where
the posterior has little mass. The exact alternative, ``J`` at every particle, costs a
forward-mode pass of T tangents per particle and evaluation (hundreds of rollouts each).

Here: the stacked basis and the blend's weights (no import of the term's modules: they import
this one); the blend itself is :func:`treeinfer.model.force_noise.mvn_log_prob`, the run's term
:class:`treeinfer.model.force_noise_model.ForceNoiseModel`. A stacked basis is a
:class:`~treeinfer.model.force_noise.ForceNoiseBasis` whose arrays carry a
leading reference axis (``vectors [K, B, T, T]``, ``values [K, B, T]``, ``slope [K, B, T, 2R]``,
``theta_ref [K, 2R]``; ``n_pad [B]`` shared): one pytree, so the likelihood's data and jitted
programs take it as they take one basis. Predictive bands use the first reference's ``diag C``
(:func:`primary`; the references' force-induced variances differ by the branch's compliance, a
few percent of a band dominated by sigma_x on the standard problem).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "LOCAL_SCALE",
    "check_references",
    "is_stacked",
    "primary",
    "reference_weights",
    "split",
    "stack",
]

# log units: the blend's length scale, the bias correction's trust radius
# (treeinfer.model.force_noise.BIAS_TRUST), within which one linearisation is accurate
LOCAL_SCALE = 0.5


def is_stacked(basis) -> bool:
    """Whether ``basis`` holds several references (a leading axis on its arrays)."""
    return basis is not None and basis.theta_ref is not None and np.ndim(basis.theta_ref) == 2


def split(basis) -> list:
    """The single-reference bases of a stacked ``basis`` (``[basis]`` when it is not stacked)."""
    if not is_stacked(basis):
        return [basis]
    k = np.shape(basis.theta_ref)[0]
    return [
        type(basis)(
            basis.vectors[i],
            basis.values[i],
            basis.n_pad,
            None if basis.slope is None else basis.slope[i],
            basis.theta_ref[i],
        )
        for i in range(k)
    ]


def stack(bases):
    """One stacked basis of single-reference ``bases`` (the one basis itself when there is one)."""
    bases = list(bases)
    if len(bases) == 1:
        return bases[0]
    first = bases[0]
    slopes = [b.slope for b in bases]
    return type(first)(
        np.stack([np.asarray(b.vectors) for b in bases]),
        np.stack([np.asarray(b.values) for b in bases]),
        first.n_pad,
        None if any(s is None for s in slopes) else np.stack([np.asarray(s) for s in slopes]),
        np.stack([np.asarray(b.theta_ref, float) for b in bases]),
    )


def primary(basis):
    """The first reference's basis (the predictive bands' ``diag C``; module docstring)."""
    return split(basis)[0]


def reference_weights(theta_gains, refs) -> jax.Array:
    """``[N, K]`` blend weights of the references ``refs [K, 2R]`` at ``theta_gains [N, 2R]``
    (module docstring)."""
    th = jnp.asarray(theta_gains)
    r = jnp.asarray(refs, th.dtype)
    d2 = jnp.sum((th[:, None, :] - r[None]) ** 2, axis=-1)
    return jax.nn.softmax(-0.5 * d2 / LOCAL_SCALE**2, axis=-1)


def check_references(reference, n_gains: int) -> np.ndarray:
    """``reference`` as ``[2R]`` or ``[K, 2R]`` (one per lobe) finite log gains, else
    :class:`treeinfer.errors.ConfigError` naming the option."""
    from ..errors import ConfigError

    ref = np.asarray(reference, float)
    if ref.ndim == 2 and len(ref) == 1:
        ref = ref[0]
    if ref.ndim not in (1, 2) or ref.shape[-1] != n_gains or not np.all(np.isfinite(ref)):
        raise ConfigError(
            f"force_noise_reference: expected {n_gains} finite log gains (or rows of them, one "
            f"per reference), got {ref.tolist()}"
        )
    return ref
