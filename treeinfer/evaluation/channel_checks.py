"""The fit verdict's posterior predictive checks on the observation channels a run was trained
with (markers, inclinometers: :mod:`treeinfer.data.channels`, issue 30).

The same checks as the displacement's (:mod:`treeinfer.evaluation.ppc`), per sensor (the
channels of one sensor on several pulls pooled, as they share one noise scale):

* **coverage** of the 95% predictive band of the training channel data
  (:func:`treeinfer.evaluation.channel_bands.channel_bands`: the particles' simulated channel
  plus each particle's noise draw);
* **standardised residuals**: each channel component's residual whitened by the Cholesky factor
  of its predictive covariance (the particles' spread plus the channel's white noise sigma^2 I:
  :func:`treeinfer.evaluation.ppc.standardised_residuals`): mean, std and tails;
* **lag-1 autocorrelation** and Ljung-Box of those residuals.

:func:`treeinfer.evaluation.ppc.ppc_findings` turns them into findings: too many training
samples outside the band is ``poor_fit`` (the channel's bands do not hold its own data);
autocorrelated residuals, a bias or a noise scale that misstates the scatter are warnings. Each
finding names the sensor. A sensor without a noise scale (none inferred or given) has a
parameter band only: its coverage is reported, never judged.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..errors import ConfigError, SimulationError


def sensor_checks(bands: Sequence, level: float = 0.95) -> tuple[list[str], list[str], dict]:
    """``(poor, warn, measures)`` of the channels' bands (:class:`~.channel_bands.ChannelBand`
    with ``draws``), one set of checks per sensor; ``measures``: per sensor ``{channels,
    fraction_outside, ppc}`` (:class:`~.ppc.PPCStats` as a dict)."""
    from .ppc import ppc_findings, ppc_stats, standardised_residuals

    groups: dict[str, list] = {}
    for b in bands:
        groups.setdefault(b.channel.sensor or b.channel.name, []).append(b)
    poor, warn, measures = [], [], {}
    for key, group in groups.items():
        noisy = all(b.sigma is not None for b in group)
        series, outside, n = [], 0, 0
        for b in group:
            lo, hi = b.band()
            rec = np.asarray(b.recorded, float)
            outside += int(np.sum((rec < lo) | (rec > hi)))
            n += rec.size
            if not noisy or b.draws is None:
                continue
            nvar = np.asarray(b.sigma, float) ** 2
            for j in range(rec.shape[1]):
                series += standardised_residuals(rec[None, :, j], b.draws[:, None, :, j],
                                                 noise_variance=nvar)  # fmt: skip
        frac = outside / max(n, 1)
        stats = ppc_stats(series, frac)
        p, w, meas = ppc_findings(stats, level, noise_model=noisy)
        kind = group[0].channel.kind
        where = group[0].channel.point.label()
        name = f"channel {key} ({kind} at {where})"
        poor += [f"{name}: {m}" for m in p]
        warn += [f"{name}: {m.replace('training points', 'training samples')}" for m in w]
        measures[key] = {
            "channels": [b.channel.name for b in group],
            "fraction_outside": float(frac),
            "band": "predictive" if noisy else "parameter",
            "ppc": meas["ppc"],
        }
    return poor, warn, measures


def channel_verdict(verdict, problem, posterior, stable, trajectories, level: float = 0.95):
    """``(verdict, bands)``: the run's :class:`~.checks.FitVerdict` with the channels' checks
    (:func:`sensor_checks` on the training channels ``problem.spec.channels``) merged in
    (``measures["channels"]``; a poor channel makes the run ``poor_fit``, a warning at least
    ``warning``), and the training bands (for the run folder's figure); the verdict unchanged
    and ``[]`` for a problem without channels."""
    from .channel_bands import channel_bands
    from .checks import FitVerdict

    spec = getattr(problem, "spec", None)
    channels = tuple(getattr(spec, "channels", ()) or ())
    if not channels:
        return verdict, []
    grasp = spec.grasp_fraction
    try:
        bands = channel_bands(
            problem.sim, posterior.theta, list(problem.labels), channels, trajectories,
            problem.settings, stable, level=level, model=getattr(problem, "model", None),
            grasp_fraction=None if grasp is None else np.atleast_1d(np.asarray(grasp, float)),
        )  # fmt: skip
    except (ConfigError, SimulationError) as e:
        status = "warning" if verdict.status == "ok" else verdict.status
        reason = f"observation channels not checked: {e}"
        return FitVerdict(status, [*verdict.reasons, reason], verdict.measures), []
    poor, warn, meas = sensor_checks(bands, level)
    status = verdict.status
    if poor:
        status = "poor_fit"
    elif warn and status == "ok":
        status = "warning"
    measures = {**verdict.measures, "channels": meas}
    return FitVerdict(status, [*verdict.reasons, *poor, *warn], measures), bands
