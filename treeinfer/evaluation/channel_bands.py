"""Predictive bands, metrics and plots of observation channels besides the grasp point
(markers, inclinometers: :mod:`treeinfer.data.channels`, issue 30).

For every posterior particle the channel is simulated (:mod:`treeinfer.sim.observe`) and
interpolated at the channel's own sample times (:func:`treeinfer.model.channels.gather`); the
*parameter band* is the particles' 2.5-97.5% quantiles, the *predictive band* adds each particle's
channel noise (a Gaussian draw with its ``sigma[name]``, or the given noise) before the
quantiles, as the displacement's band does (:func:`treeinfer.evaluation.metrics.
noisy_predictive_interval`). A channel of new data takes the noise of the run's channel with the
same name, else of the run's channels at the same point and of the same kind (pooled in log),
else its own given noise; without any, only the parameter band is scored.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple, Sequence

import jax
import numpy as np

from ..data.channels import Channel
from ..errors import ConfigError

LEVEL = 0.95


class ChannelBand(NamedTuple):
    """One channel's bands: ``time [S]`` s, ``recorded``, ``mean``, ``lower``, ``upper``,
    ``predictive_lower``, ``predictive_upper`` ``[S, C]`` (SI; the predictive pair None without
    a noise scale), ``channel`` (the :class:`Channel`)."""

    channel: Channel
    time: np.ndarray
    recorded: np.ndarray
    mean: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    predictive_lower: np.ndarray | None
    predictive_upper: np.ndarray | None
    draws: np.ndarray | None = None  # [P, S, C] the stable particles' simulated channel
    sigma: np.ndarray | None = None  # [P] their noise std (SI), None without a noise scale

    @property
    def has_recording(self) -> bool:
        """False for a channel predicted under a new force (no recorded values, NaN)."""
        return bool(np.isfinite(self.recorded).any())

    def band(self) -> tuple[np.ndarray, np.ndarray]:
        """The band a recording is compared with: predictive when a noise scale is known."""
        if self.predictive_lower is not None:
            return self.predictive_lower, self.predictive_upper
        return self.lower, self.upper

    def metrics(self) -> dict:
        """``{band, pct_outside, rmse, band_width, samples}`` (SI units of the channel);
        ``pct_outside`` and ``rmse`` None without a recording."""
        lo, hi = self.band()
        rec = self.has_recording
        out = (self.recorded < lo) | (self.recorded > hi)
        return {
            "kind": self.channel.kind,
            "point": self.channel.point.label(),
            "recording": self.channel.recording,
            "band": "predictive" if self.predictive_lower is not None else "parameter",
            "pct_outside": float(100.0 * out.mean()) if rec else None,
            "rmse": float(np.sqrt(np.mean((self.recorded - self.mean) ** 2))) if rec else None,
            "band_width": float(np.mean(hi - lo)),
            "samples": int(self.recorded.size),
            "unit": {"position": "m", "angle": "rad", "image": "px"}[self.channel.kind],
        }


def _noise_draws(theta, labels, settings, channels: Sequence[Channel]) -> list:
    """Per channel: ``[P]`` noise std draws (SI), or None (no noise known)."""
    labels = list(labels)
    trained = {c["name"]: c for c in (settings or {}).get("channels", [])}
    out = []
    for ch in channels:
        col = f"sigma[{ch.sensor or ch.name}]"
        if col in labels:
            out.append(np.exp(theta[:, labels.index(col)]))
            continue
        same = [
            f"sigma[{c.get('sensor', n)}]"
            for n, c in trained.items()
            if c["kind"] == ch.kind
            and c["link"] == ch.point.link
            and c.get("fraction") == ch.point.fraction
            and c.get("distance") == ch.point.distance
        ]
        cols = [labels.index(c) for c in dict.fromkeys(same) if c in labels]
        given = [c["noise"] for n, c in trained.items() if f"sigma[{c.get('sensor', n)}]" in same]
        if cols:
            out.append(np.exp(np.mean(theta[:, cols], axis=1)))
        elif ch.noise is not None:
            out.append(np.full(len(theta), float(ch.noise)))
        elif given and all(g is not None for g in given):
            out.append(np.full(len(theta), float(np.exp(np.mean(np.log(given))))))
        else:
            out.append(None)
    return out


def channel_bands(
    sim,
    theta,
    labels,
    channels: Sequence[Channel],
    trajectories,
    settings: dict | None = None,
    particle_ok=None,
    level: float = LEVEL,
    seed: int = 0,
    model=None,
    grasp_fraction=None,
) -> list[ChannelBand]:
    """The bands of ``channels`` for the posterior particles ``theta [P, D]`` (columns
    ``labels``; gains first) under the ``trajectories``' forces (each channel on the pull it
    names). ``settings``: the run's problem settings (its channels, to find a noise scale);
    ``particle_ok`` [P]: particles to use (stable ones); ``model``: the run's
    :class:`treeinfer.inference.static.Model` (None: the paper's dynamic model) with its pulls,
    at ``grasp_fraction`` (None, a scalar or [B]). A channel whose values are NaN (predicted
    under a new force: :func:`run_channels`) gets its bands only."""
    from ..data.trajectories import stack_trajectories
    from ..inference.static.channels import model_features
    from ..model.channels import channel_layout, gather

    theta = np.atleast_2d(np.asarray(theta, float))
    if particle_ok is not None:
        theta = theta[np.asarray(particle_ok, bool)]
    trajs = list(trajectories)
    obs = stack_trajectories(trajs)
    layout = channel_layout(  # the noise here only stands in: the bands take the run's
        sim,
        [c if c.noise is not None else c._replace(noise=1.0) for c in channels],
        [t.source for t in trajs],
        [float(t.time[0]) for t in trajs],
        [t.n_steps for t in trajs],
    )
    feats, ok = model_features(
        sim, model, theta, np.asarray(obs.force), layout.features, grasp_fraction
    )
    pred = np.asarray(jax.device_get(gather(layout, feats, ok)), float)  # [P, S]
    good = np.all(np.isfinite(pred), axis=1)
    if good.sum() < 2:
        raise ConfigError("channel bands: fewer than two particles give stable simulations")
    pred, theta = pred[good], theta[good]
    sig = _noise_draws(theta, labels, settings, channels)
    rng = np.random.default_rng(seed)
    q = (0.5 - level / 2, 0.5 + level / 2)
    bands = []
    for c_i, ch in enumerate(channels):
        sel = layout.channel == c_i
        n_s, n_c = len(ch.time), len(ch.components)
        p = pred[:, sel].reshape(len(pred), n_c, n_s).transpose(0, 2, 1)  # [P, S, C]
        lo, hi = np.quantile(p, q, axis=0)
        plo = phi = None
        if sig[c_i] is not None:
            # many noise draws per particle so the band's quantiles are smooth
            reps = max(1, 2000 // len(p))
            noisy = (
                np.repeat(p, reps, axis=0)
                + rng.normal(size=(len(p) * reps, n_s, n_c))
                * (np.repeat(sig[c_i], reps)[:, None, None])
            )
            plo, phi = np.quantile(noisy, q, axis=0)
        bands.append(ChannelBand(ch, ch.time, ch.values, p.mean(0), lo, hi, plo, phi, p, sig[c_i]))
    return bands


def run_channels(settings: dict | None, recording: str, time) -> tuple[Channel, ...]:
    """The sensors a run was trained with (its problem settings' ``channels``), one channel per
    sensor (channels of one sensor on several pulls are one), placed on a new pull ``recording``
    sampled at ``time [T]`` s, with NaN values: what :func:`channel_bands` predicts for a force
    the sensors never saw (``treeinfer predict``). Named by the sensor; the noise is the
    sensor's inferred column (found by that name) or its given noise."""
    from ..data.channels import NamedPoint

    out, seen = [], set()
    for c in (settings or {}).get("channels", []):
        key = c.get("sensor") or c["name"]
        if key in seen or c["kind"] == "image":  # a run records no camera: not predictable
            continue
        seen.add(key)
        point = NamedPoint(c["link"], c.get("distance"), c.get("fraction"))
        comps = tuple(c["components"])
        t = np.asarray(time, float)
        values = np.full((len(t), len(comps)), np.nan)
        out.append(Channel(key, c["kind"], recording, point, comps, t, values, c.get("noise"),
                           "the run's channels", sensor=key))  # fmt: skip
    return tuple(out)


def band_csv(band: ChannelBand) -> str:
    """A channel's bands as CSV text: time, then per component recorded, mean, lower, upper
    (and predictive_lower, predictive_upper), SI units."""
    cols = ["time"]
    data = [band.time[:, None]]
    for j, c in enumerate(band.channel.components):
        parts = [("recorded", band.recorded), ("mean", band.mean), ("lower", band.lower)]
        parts.append(("upper", band.upper))
        if band.predictive_lower is not None:
            parts += [("predictive_lower", band.predictive_lower)]
            parts += [("predictive_upper", band.predictive_upper)]
        for name, arr in parts:
            cols.append(f"{c}_{name}")
            data.append(arr[:, j : j + 1])
    body = np.concatenate(data, axis=1)
    lines = [",".join(cols)] + [",".join(f"{x:.9g}" for x in row) for row in body]
    return "\n".join(lines) + "\n"


def plot_channel_bands(bands: Sequence[ChannelBand]):
    """One panel per channel component: recorded points and the bands. Returns ``(fig, axes)``."""
    import matplotlib.pyplot as plt

    panels = [(b, j) for b in bands for j in range(len(b.channel.components))]
    ncol = min(3, len(panels))
    nrow = -(-len(panels) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 2.8 * nrow), squeeze=False)
    for ax, (b, j) in zip(axes.flat, panels):
        scale, unit = {"position": (1e3, "mm"), "angle": (1e3, "mrad"), "image": (1.0, "px")}[
            b.channel.kind
        ]
        if b.predictive_lower is not None:
            ax.fill_between(b.time, scale * b.predictive_lower[:, j], scale *
                            b.predictive_upper[:, j], color="C0", alpha=0.2,
                            label="95% predictive")  # fmt: skip
        ax.fill_between(b.time, scale * b.lower[:, j], scale * b.upper[:, j], color="C0",
                        alpha=0.45, label="95% parameter")  # fmt: skip
        ax.plot(b.time, scale * b.mean[:, j], color="C0", lw=1)
        if b.has_recording:  # a channel predicted under a new force has none
            ax.plot(b.time, scale * b.recorded[:, j], ".", color="k", ms=2, label="recorded")
        comp = b.channel.components[j]
        ax.set_title(f"{b.channel.name}: {b.channel.kind} {comp} at {b.channel.point.label()}",
                     fontsize=8)  # fmt: skip
        ax.set_xlabel("time [s]")
        ax.set_ylabel(f"[{unit}]")
    for ax in list(axes.flat)[len(panels) :]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize=7)
    fig.tight_layout()
    return fig, axes


def write_channel_outputs(out: Path, bands: Sequence[ChannelBand], formats=("png",)) -> dict:
    """``out/channels/<name>_prediction.csv`` per channel and ``out/channels.png``; returns the
    metrics per channel name."""
    from ..io.atomic import atomic_write_text
    from .plots import save_figure

    (Path(out) / "channels").mkdir(parents=True, exist_ok=True)
    for b in bands:
        atomic_write_text(Path(out) / "channels" / f"{b.channel.name}_prediction.csv", band_csv(b))
    fig, _ = plot_channel_bands(bands)
    save_figure(fig, Path(out) / "channels.png", formats=formats)
    return {b.channel.name: b.metrics() for b in bands}
