"""The generative likelihood of observation channels besides the grasp point (issue 30):
markers and inclinometers at named points (:mod:`treeinfer.data.channels`).

Each channel ``c`` adds ``sum_s log N(y_cs | g_cs(theta), sigma_c^2)``: ``g`` is the simulated
channel (:mod:`treeinfer.sim.observe`: forward kinematics of the rollout's joint angles)
interpolated linearly at the channel's own sample times, ``sigma_c`` the channel's noise std,
given in ``channels.yaml`` or inferred as a column ``sigma[sensor]`` of theta (``log sigma_c``,
after every other column; channels with the same ``sensor`` share one, a channel without one has
its own ``sigma[name]``) with the displacement noise's weakly informative prior: log-flat from
the channel's resolution floor to its data range (:class:`treeinfer.model.noise.NoisePrior`).
The displacement term (with its force-noise correction) is unchanged; the channel terms are
independent of it and of each other (white noise per channel).

:func:`with_channels` adds the terms to a problem's :class:`~treeinfer.model.likelihood.
LikelihoodTerms`; the simulator rollout of the channels is a black box with central-difference
derivatives (:func:`treeinfer.model.gradients.finite_difference_jvp`), as the displacement's.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..data.channels import Channel, sample_weights
from ..errors import ConfigError
from ..sim.observe import Feature, feature_for, simulate_features
from . import noise
from .gains import gains_from_theta
from .gradients import autodiff_value_and_grad, finite_difference_jvp

# the smallest noise scale a channel's prior allows (sensor resolution), SI units
RESOLUTION = {"position": 1e-6, "angle": 1e-6, "image": 1e-3}


class ChannelLayout(NamedTuple):
    """The channels' samples as flat host arrays (S samples over all channels), built once.

    features: the distinct sensed points (:class:`treeinfer.sim.observe.Feature`).
    row [S]: the pull (row of the observations); index, weight [S]: linear interpolation on
    the pull's grid; feature, axis [S]: which feature and world axis; values [S] SI;
    channel [S]: index into ``channels``. sigma [C]: given noise (SI) or NaN where inferred.
    inferred: the noise columns' keys, in column order: a channel's ``sensor`` (the channels
    of one sensor on several pulls share one noise scale), else its name. column [C]: each
    channel's noise column (-1: given). priors: the columns'
    :class:`~treeinfer.model.noise.NoisePrior`. channels: the channels.
    """

    features: tuple[Feature, ...]
    row: np.ndarray
    index: np.ndarray
    weight: np.ndarray
    feature: np.ndarray
    axis: np.ndarray
    values: np.ndarray
    channel: np.ndarray
    sigma: np.ndarray
    inferred: tuple[str, ...]
    column: np.ndarray
    priors: tuple
    channels: tuple[Channel, ...]

    @property
    def labels(self) -> tuple[str, ...]:
        """theta's column labels of the inferred channel noises."""
        return tuple(f"sigma[{key}]" for key in self.inferred)


def channel_layout(
    sim, channels: Sequence[Channel], recordings: Sequence[str], t0: Sequence[float], n_steps
) -> ChannelLayout:
    """The :class:`ChannelLayout` of ``channels`` on the pulls named ``recordings`` (file names,
    in the observations' row order) that start at ``t0`` s and have ``n_steps`` samples each
    (on the simulator's ``obs_dt``)."""
    names = [Path(r).name for r in recordings]
    feats: list[Feature] = []
    cols = {k: [] for k in ("row", "index", "weight", "feature", "axis", "values", "channel")}
    sigma, column, inferred = [], [], []
    spans: dict[str, list] = {}  # column key -> [floor, ceiling, samples]
    for c_i, ch in enumerate(channels):
        if ch.recording not in names:
            raise ConfigError(
                f"{ch.source}: channel '{ch.name}' observed the pull '{ch.recording}', which is "
                f"not in the data (pulls: {', '.join(names)})"
            )
        b = names.index(ch.recording)
        length = float(sim.branches[ch.point.link][1]) if ch.point.link in sim.branches else 1.0
        f = feature_for(sim, ch.kind, ch.point.link, ch.point.fraction_of(length), ch.camera)
        if f not in feats:
            feats.append(f)
        n_b = int(np.atleast_1d(n_steps)[b] if np.ndim(n_steps) else n_steps)
        i, w = sample_weights(ch.time, float(t0[b]), sim.obs_dt, n_b)
        s = len(ch.time)
        for a_j, a in enumerate(ch.axes):
            cols["row"].append(np.full(s, b))
            cols["index"].append(i)
            cols["weight"].append(w)
            cols["feature"].append(np.full(s, feats.index(f)))
            cols["axis"].append(np.full(s, a))
            cols["values"].append(ch.values[:, a_j])
            cols["channel"].append(np.full(s, c_i))
        if ch.noise is None:
            sigma.append(np.nan)
            key = ch.sensor or ch.name
            if key not in inferred:
                inferred.append(key)
                spans[key] = [math.inf, 0.0, 0]
            column.append(inferred.index(key))
            rng = ch.value_range()
            if not rng > 0:
                raise ConfigError(
                    f"{ch.source}: channel '{ch.name}' does not vary: no noise scale to infer; "
                    "give its noise in channels.yaml"
                )
            sp = spans[key]
            sp[0] = min(sp[0], RESOLUTION[ch.kind], rng / 100.0)
            sp[1] = max(sp[1], rng)
            sp[2] += s * len(ch.axes)
        else:
            sigma.append(float(ch.noise))
            column.append(-1)
    priors = [
        noise.NoisePrior(lo, hi, 0.5 / math.sqrt(n), 1.0, "resolution")
        for lo, hi, n in (spans[k] for k in inferred)
    ]
    cat = {k: np.concatenate(v) for k, v in cols.items()}
    return ChannelLayout(
        tuple(feats),
        cat["row"].astype(np.int32),
        cat["index"].astype(np.int32),
        cat["weight"].astype(np.float32),
        cat["feature"].astype(np.int32),
        cat["axis"].astype(np.int32),
        cat["values"].astype(np.float32),
        cat["channel"].astype(np.int32),
        np.asarray(sigma, float),
        tuple(inferred),
        np.asarray(column, np.int32),
        tuple(priors),
        tuple(channels),
    )


def gather(layout: ChannelLayout, features: jax.Array, stable: jax.Array) -> jax.Array:
    """``[P, S]`` simulated channel samples from ``features [P, B, T, F, 3]`` (NaN where the
    pull's rollout was unstable)."""
    r, i, f, a = (jnp.asarray(x) for x in (layout.row, layout.index, layout.feature, layout.axis))
    w = jnp.asarray(layout.weight, features.dtype)
    lo = features[:, r, i, f, a]
    hi = features[:, r, i + 1, f, a] if features.shape[2] > 1 else lo
    return jnp.where(stable[:, r], (1.0 - w) * lo + w * hi, jnp.nan)


def channel_predictions(
    sim, layout: ChannelLayout, kp, kd, forces, grasp_fraction=None, direction=None
):
    """``[P, S]`` simulated channel samples for gains ``kp, kd [P, R]`` under ``forces [B, T]``."""
    ro = simulate_features(sim, kp, kd, forces, layout.features, grasp_fraction, direction)
    return gather(layout, ro.features, ro.stable)


def channel_log_likelihood(
    sim,
    layout: ChannelLayout,
    forces,
    grasp_fraction=None,
    direction=None,
    first_column: int | None = None,
    rel_step: float | None = None,
    n_gains: int | None = None,
    features=None,
):
    """``theta [N, D] -> [N]`` nats: the channels' Gaussian terms. Gains are theta's first
    ``n_gains`` columns (default 2R, the paper's ``[log Kp, log Kd]``); ``features``:
    ``gains [N, n_gains] -> (features [N, B, T, F, 3], stable [N, B])`` of another model
    (:func:`treeinfer.inference.static.channels.model_features`; default: the paper's rollout);
    the inferred ``log sigma`` columns start at ``first_column`` (default: the last
    ``len(layout.inferred)`` columns)."""
    n_gains = 2 * sim.n_joints if n_gains is None else int(n_gains)
    forces = jnp.asarray(forces, sim.dtype)
    y = jnp.asarray(layout.values)
    chan = jnp.asarray(layout.channel)
    fixed = jnp.asarray(np.nan_to_num(layout.sigma, nan=1.0), sim.dtype)
    k = len(layout.inferred)
    slot = jnp.asarray(layout.column)

    def predict(theta_gains):
        if features is None:
            kp, kd = gains_from_theta(theta_gains, sim.n_joints)
            return channel_predictions(sim, layout, kp, kd, forces, grasp_fraction, direction)
        return gather(layout, *features(theta_gains))

    sim_fn = finite_difference_jvp(predict, rel_step)

    def loglik(theta):
        theta = jnp.asarray(theta)
        c0 = theta.shape[1] - k if first_column is None else first_column
        pred = sim_fn(theta[:, :n_gains])  # [N, S]
        log_s = jnp.log(fixed)[None, :] * jnp.ones((theta.shape[0], 1), theta.dtype)
        if k:
            log_s = jnp.where(
                slot[None, :] >= 0, theta[:, c0 + jnp.maximum(slot, 0)], log_s
            )  # [N, C]
        ls = log_s[:, chan]  # [N, S]
        z = (y[None, :] - pred) * jnp.exp(-ls)
        lp = -0.5 * z**2 - ls - 0.5 * math.log(2 * math.pi)
        total = jnp.sum(lp, axis=-1)
        return jnp.where(jnp.isfinite(total), total, -jnp.inf)

    return loglik


def with_channels(
    terms, sim, obs, layout: ChannelLayout, grasp_fraction=None, rel_step=None, n_gains=None,
    features=None,
):  # fmt: skip
    """``terms`` (:class:`~treeinfer.model.likelihood.LikelihoodTerms` of a generative
    likelihood) with the channels' terms added and their noise columns appended to theta;
    ``n_gains``, ``features``: another model's gain columns and channel rollout (as
    :func:`channel_log_likelihood`; the inference layer builds them for any
    :class:`treeinfer.inference.static.Model`: dynamic or static, each pull at its branch and
    direction); None: the paper's.
    The bucketed sampler programs and the start pipeline's residual density do not cover the
    channels: ``data_of``/``loglik_of``/``residual_loglik`` are None (the run takes the problem's
    own log-density: :func:`treeinfer.inference.start_pipeline.auto_start`)."""
    if terms.black_box:
        raise ConfigError(
            "observation channels: need a generative likelihood (--likelihood gaussian, "
            "student_t or ar1), not the Boltzmann loss"
        )
    n_gains = 2 * sim.n_joints if n_gains is None else int(n_gains)
    d0 = n_gains + len(terms.extra_labels)
    ch_ll = channel_log_likelihood(
        sim, layout, obs.force, grasp_fraction, None, d0, rel_step, n_gains, features
    )
    base_ll, base_prior = terms.log_likelihood, terms.extra_log_prior
    priors = layout.priors

    def loglik(theta):
        theta = jnp.asarray(theta)
        return base_ll(theta[:, :d0]) + ch_ll(theta)

    def log_prior(theta):
        theta = jnp.asarray(theta)
        total = jnp.zeros(theta.shape[:1], theta.dtype)
        if base_prior is not None:
            total = total + base_prior(theta[:, :d0])
        for j, p in enumerate(priors):
            total = total + p.log_prob(theta[:, d0 + j])
        return total

    bounds = np.array([p.log_bounds for p in priors]).reshape(-1, 2)
    desc = [
        f"channel {ch.name}: {ch.kind} of {ch.point.label()} ({', '.join(ch.components)}), "
        f"{len(ch.time)} samples at {ch.rate:.4g} Hz, noise "
        + (f"{ch.noise:.3g} (given)" if ch.noise is not None else "inferred")
        for ch in layout.channels
    ]
    settings = {
        **terms.settings,
        "channels": [channel_record(ch) for ch in layout.channels],
        "channel_noise_columns": len(priors),
    }
    init = terms.extra_init
    if init is not None and len(priors):
        lo = np.concatenate([np.asarray(init[0]), bounds[:, 0]])
        hi = np.concatenate([np.asarray(init[1]), bounds[:, 1]])
        init = (lo, hi)
    return terms._replace(
        log_likelihood=loglik,
        value_and_grad=autodiff_value_and_grad(loglik),
        extra_labels=tuple(terms.extra_labels) + layout.labels,
        extra_lower=np.concatenate([np.asarray(terms.extra_lower), bounds[:, 0]]),
        extra_upper=np.concatenate([np.asarray(terms.extra_upper), bounds[:, 1]]),
        extra_log_prior=log_prior if (base_prior is not None or priors) else None,
        settings=settings,
        description="\n".join([terms.description, *desc]),
        data_of=None,
        loglik_of=None,
        residual_loglik=None,
        extra_init=init,
    )


TOLERANCE_FLOOR = 2e-5  # m: the finest step accuracy the channels ask for (substeps grow as 1/sqrt)


def channel_tolerance(channels: Sequence[Channel], tree) -> float | None:
    """m, an accuracy target of the simulation step that keeps each channel's discretisation
    error at a tenth of its noise, or None (no position or angle channel). The step's accuracy
    control measures the grasp point's displacement, so a channel's noise is expressed as a
    displacement: a marker's as it is, an inclinometer's times its link's length (the lever that
    turns an angle error into a displacement error). The noise is the given one, else a robust
    estimate from the channel (MAD of second differences / sqrt(6), as for the displacement; at a
    low rate it also counts some of a fast signal's curvature, so it errs towards a looser step).
    Not below :data:`TOLERANCE_FLOOR`. Image channels (pixels) are left to the displacement's."""
    out = []
    for ch in channels:
        if ch.kind not in ("position", "angle") or len(ch.time) < 4:
            continue
        sigma = ch.noise
        if sigma is None:
            d2 = np.diff(np.asarray(ch.values, float), n=2, axis=0)
            mad = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0) * 1.4826
            sigma = float(np.median(mad)) / math.sqrt(6.0)
        if not sigma > 0:
            continue
        lever = tree.branch(ch.point.link).length if ch.kind == "angle" else 1.0
        out.append(0.1 * sigma * lever)
    return max(TOLERANCE_FLOOR, min(out)) if out else None


def channel_record(ch: Channel) -> dict:
    """JSON-ready description of a channel (a run's settings)."""
    return {
        "name": ch.name,
        "kind": ch.kind,
        "recording": ch.recording,
        "link": ch.point.link,
        "fraction": ch.point.fraction,
        "distance": ch.point.distance,
        "components": list(ch.components),
        "noise": ch.noise,
        "sensor": ch.sensor or ch.name,
        "samples": int(len(ch.time)),
        "rate_hz": ch.rate,
        "source": ch.source,
    }
