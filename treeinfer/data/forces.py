"""Force profiles: how hard the robot (or the simulator) pulls the grasp point down over time.

A profile is a float64 array ``[T]`` in newtons along gravity (positive = downward), on the
trajectory time grid ``t_k = k * dt``, ``k = 0 .. T - 1``, with
``T = n_steps(duration, dt) = floor(duration / dt)``.
Sample ``k`` is the force at ``t_k``; the simulator holds it over ``[t_k, t_k + dt)`` (see
:func:`treeinfer.simulator.simulate`), so the last sample's interval ends by ``duration``.

The shapes, all zero before ``start`` (rest: the branch hangs under gravity alone):

* :func:`ramp` -- linear rise from 0 at ``start`` to ``peak`` at ``start + ramp_time``, then held
  at ``peak`` to the end (a slow pull that is not let go).
* :func:`ramp_hold` -- the same rise, held at ``peak`` for ``hold_time``, a linear release back to
  0 over ``release_time``, then 0 to the end (the branch swings back and settles).
* :func:`ramp_release` -- :func:`ramp_hold` without the hold (a triangle).
* :func:`smooth_step` -- a smoothstep rise ``peak * (3 s^2 - 2 s^3)``, ``s = (t - start) /
  rise_time`` clipped to [0, 1]: a quick pull with no kink in the force (nor its slope) at
  either end, then held.

A profile may end before its shape does (e.g. a ramp longer than ``duration``): it is simply cut.

On the command line a profile is written as a compact *spec*, ``kind:key=value,...``::

    ramp:peak=20,ramp=1.0[,start=0.1]
    hold:peak=15,ramp=0.5,hold=1.0,release=0.5[,start=0]
    release:peak=10,ramp=0.8,release=0.4[,start=0]
    step:peak=5,rise=0.2[,start=0.5]

(peak in N, times in s); :func:`parse_spec` reads one, :func:`format_spec` writes one and
:func:`from_spec` samples it. :func:`random_specs` / :func:`profile_set` draw a varied, seeded set
for synthetic data sets.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from ..errors import ConfigError

__all__ = [
    "DEFAULT_PEAK_RANGE",
    "MIN_STEPS",
    "SET_KINDS",
    "SHAPES",
    "SPEC_KEYS",
    "ProfileSpec",
    "format_spec",
    "from_spec",
    "n_steps",
    "parse_spec",
    "piecewise_linear",
    "profile_set",
    "ramp",
    "ramp_hold",
    "ramp_release",
    "random_specs",
    "sample_times",
    "smooth_step",
]

# Same as treeinfer.data.trajectories.MIN_ROWS (the second-order velocity scheme needs 3 samples);
# not imported so that this module stays free of JAX.
MIN_STEPS = 3
DEFAULT_PEAK_RANGE = (2.0, 8.0)  # N: sags of a few cm to a few tens of cm on the example trees
_STEP_TOL = 1e-9  # relative slack when dividing duration by dt (0.3 / 0.1 = 2.9999999999999996)


# ---- time grid ------------------------------------------------------------------------------
def _number(v, fld: str, where: str) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: {fld} must be a number, got {v!r}") from None
    if not math.isfinite(f):
        raise ConfigError(f"{where}: {fld} must be finite, got {v!r}")
    return f


def _positive(v, fld: str, where: str) -> float:
    f = _number(v, fld, where)
    if f <= 0:
        raise ConfigError(f"{where}: {fld} must be positive, got {v!r}")
    return f


def _non_negative(v, fld: str, where: str) -> float:
    f = _number(v, fld, where)
    if f < 0:
        raise ConfigError(f"{where}: {fld} must be >= 0, got {v!r}")
    return f


def n_steps(duration: float, dt: float) -> int:
    """Number of samples T of a profile lasting ``duration`` seconds sampled every ``dt`` s:
    ``floor(duration / dt)`` (so ``T * dt <= duration``: the last sample's interval ends by
    ``duration``). Raises :class:`ConfigError` when ``dt <= 0`` or ``T < MIN_STEPS``."""
    duration = _positive(duration, "duration", "force profile")
    dt = _positive(dt, "dt", "force profile")
    t = math.floor(duration / dt * (1.0 + _STEP_TOL))
    if t < MIN_STEPS:
        raise ConfigError(
            f"force profile: duration {duration:g} s at dt {dt:g} s gives {t} sample(s); "
            f"at least {MIN_STEPS} are needed (lengthen the duration or shorten dt)"
        )
    return t


def sample_times(duration: float, dt: float) -> np.ndarray:
    """[T] s, the sample times ``k * dt`` of a profile (the trajectory CSV's time column)."""
    return np.arange(n_steps(duration, dt), dtype=float) * float(dt)


def piecewise_linear(
    knot_times: Sequence[float], knot_forces: Sequence[float], duration: float, dt: float
) -> np.ndarray:
    """[T] N: linear interpolation through ``(knot_times, knot_forces)`` at the sample times,
    constant (the first/last knot's force) outside the knots. ``knot_times`` in s must be
    strictly increasing. Built on ``numpy.interp``."""
    xp = np.asarray(knot_times, dtype=float)
    fp = np.asarray(knot_forces, dtype=float)
    if xp.ndim != 1 or xp.shape != fp.shape or xp.size == 0:
        raise ConfigError(
            f"piecewise_linear: need equally long 1-D knot lists, got {xp.shape} and {fp.shape}"
        )
    if not (np.all(np.isfinite(xp)) and np.all(np.isfinite(fp))):
        raise ConfigError("piecewise_linear: knots must be finite")
    if np.any(np.diff(xp) <= 0):
        raise ConfigError(
            f"piecewise_linear: knot times must be strictly increasing, got {xp.tolist()}"
        )
    return np.interp(sample_times(duration, dt), xp, fp)


def _check_start(start: float, duration: float, where: str) -> float:
    start = _non_negative(start, "start", where)
    if start >= float(duration):
        raise ConfigError(
            f"{where}: start {start:g} s is not before the end of the profile "
            f"({float(duration):g} s); the force would be zero throughout"
        )
    return start


# ---- shapes ---------------------------------------------------------------------------------
def ramp(
    peak: float, ramp_time: float, duration: float, dt: float, start: float = 0.0
) -> np.ndarray:
    """[T] N: 0 until ``start``, linear rise to ``peak`` (N) at ``start + ramp_time`` (s), then
    ``peak`` to the end."""
    where = "ramp"
    peak = _number(peak, "peak", where)
    ramp_time = _positive(ramp_time, "ramp_time", where)
    start = _check_start(start, duration, where)
    return piecewise_linear([start, start + ramp_time], [0.0, peak], duration, dt)


def ramp_hold(
    peak: float,
    ramp_time: float,
    hold_time: float,
    release_time: float,
    duration: float,
    dt: float,
    start: float = 0.0,
) -> np.ndarray:
    """[T] N: 0 until ``start``; linear rise to ``peak`` over ``ramp_time``; ``peak`` for
    ``hold_time`` (may be 0); linear release to 0 over ``release_time``; then 0 to the end.
    Times in s."""
    where = "ramp_hold"
    peak = _number(peak, "peak", where)
    ramp_time = _positive(ramp_time, "ramp_time", where)
    hold_time = _non_negative(hold_time, "hold_time", where)
    release_time = _positive(release_time, "release_time", where)
    start = _check_start(start, duration, where)
    top = start + ramp_time
    times, forces = [start, top], [0.0, peak]
    if hold_time > 0:  # a zero hold would repeat a knot time
        times.append(top + hold_time)
        forces.append(peak)
    times.append(top + hold_time + release_time)
    forces.append(0.0)
    return piecewise_linear(times, forces, duration, dt)


def ramp_release(
    peak: float,
    ramp_time: float,
    release_time: float,
    duration: float,
    dt: float,
    start: float = 0.0,
) -> np.ndarray:
    """[T] N: a triangle, :func:`ramp_hold` with ``hold_time = 0``."""
    return ramp_hold(peak, ramp_time, 0.0, release_time, duration, dt, start)


def smooth_step(
    peak: float, rise_time: float, duration: float, dt: float, start: float = 0.0
) -> np.ndarray:
    """[T] N: ``peak * (3 s^2 - 2 s^3)`` with ``s = clip((t - start) / rise_time, 0, 1)``: a rise
    from 0 to ``peak`` over ``rise_time`` s with zero slope at both ends, then held."""
    where = "smooth_step"
    peak = _number(peak, "peak", where)
    rise_time = _positive(rise_time, "rise_time", where)
    start = _check_start(start, duration, where)
    s = np.clip((sample_times(duration, dt) - start) / rise_time, 0.0, 1.0)
    return peak * s * s * (3.0 - 2.0 * s)


# ---- compact specs --------------------------------------------------------------------------
# kind -> (function, {spec key: function argument}); keys without a default are required.
SHAPES: dict[str, Callable[..., np.ndarray]] = {
    "ramp": ramp,
    "hold": ramp_hold,
    "release": ramp_release,
    "step": smooth_step,
}
SPEC_KEYS: dict[str, dict[str, str]] = {
    "ramp": {"peak": "peak", "ramp": "ramp_time", "start": "start"},
    "hold": {
        "peak": "peak",
        "ramp": "ramp_time",
        "hold": "hold_time",
        "release": "release_time",
        "start": "start",
    },
    "release": {"peak": "peak", "ramp": "ramp_time", "release": "release_time", "start": "start"},
    "step": {"peak": "peak", "rise": "rise_time", "start": "start"},
}
_OPTIONAL_KEYS = {"start"}


class ProfileSpec(NamedTuple):
    """A parsed spec: ``kind`` (a key of :data:`SHAPES`) and ``params`` {spec key: value}
    (N for ``peak``, s for the times)."""

    kind: str
    params: dict[str, float]


def _spec_help() -> str:
    return "; ".join(
        f"{k}:"
        + ",".join(f"{p}=..." for p in keys if p not in _OPTIONAL_KEYS)
        + "".join(f"[,{p}=...]" for p in keys if p in _OPTIONAL_KEYS)
        for k, keys in SPEC_KEYS.items()
    )


def parse_spec(spec: str) -> ProfileSpec:
    """Parse ``kind:key=value,...`` (see the module docstring).

    Raises:
      ConfigError: unknown kind, malformed ``key=value``, unknown, repeated or missing key, or a
        value that is not a number; the message quotes the spec and names the key.
    """
    if not isinstance(spec, str) or not spec.strip():
        raise ConfigError(
            f"force profile spec: expected 'kind:key=value,...', got {spec!r}; forms: "
            f"{_spec_help()}"
        )
    text = spec.strip()
    kind, sep, rest = text.partition(":")
    kind = kind.strip().lower()
    if kind not in SPEC_KEYS:
        raise ConfigError(
            f"force profile spec {spec!r}: unknown kind '{kind}'; choose one of "
            f"{sorted(SPEC_KEYS)} ({_spec_help()})"
        )
    allowed = SPEC_KEYS[kind]
    params: dict[str, float] = {}
    for item in rest.split(",") if sep and rest.strip() else []:
        key, eq, value = item.partition("=")
        key = key.strip().lower()
        if not eq or not key:
            raise ConfigError(
                f"force profile spec {spec!r}: expected key=value, got {item.strip()!r}"
            )
        if key not in allowed:
            raise ConfigError(
                f"force profile spec {spec!r}: unknown key '{key}' for kind '{kind}'; "
                f"allowed: {', '.join(allowed)}"
            )
        if key in params:
            raise ConfigError(f"force profile spec {spec!r}: key '{key}' given twice")
        try:
            v = float(value)
        except ValueError:
            raise ConfigError(
                f"force profile spec {spec!r}: key '{key}' must be a number, got {value.strip()!r}"
            ) from None
        if not math.isfinite(v):
            raise ConfigError(
                f"force profile spec {spec!r}: key '{key}' must be finite, got {value.strip()!r}"
            )
        params[key] = v
    missing = [k for k in allowed if k not in params and k not in _OPTIONAL_KEYS]
    if missing:
        raise ConfigError(
            f"force profile spec {spec!r}: missing key(s) {', '.join(missing)} for kind '{kind}' "
            f"(form: {kind}:"
            + ",".join(f"{k}=..." for k in allowed if k not in _OPTIONAL_KEYS)
            + ")"
        )
    return ProfileSpec(kind, params)


def format_spec(kind: str, **params: float) -> str:
    """The spec string of ``kind`` with ``params`` (spec keys); ``parse_spec`` reads it back
    exactly (values are written with ``repr``)."""
    if kind not in SPEC_KEYS:
        raise ConfigError(
            f"force profile: unknown kind '{kind}'; choose one of {sorted(SPEC_KEYS)}"
        )
    bad = sorted(set(params) - set(SPEC_KEYS[kind]))
    if bad:
        raise ConfigError(
            f"force profile '{kind}': unknown key(s) {bad}; allowed: {list(SPEC_KEYS[kind])}"
        )
    return f"{kind}:" + ",".join(
        f"{k}={float(params[k])!r}" for k in SPEC_KEYS[kind] if k in params
    )


def from_spec(spec: str | ProfileSpec, duration: float, dt: float) -> np.ndarray:
    """[T] N: the profile a spec describes, sampled every ``dt`` s for ``duration`` s."""
    ps = spec if isinstance(spec, ProfileSpec) else parse_spec(spec)
    keys = SPEC_KEYS[ps.kind]
    kwargs = {keys[k]: v for k, v in ps.params.items()}
    try:
        return SHAPES[ps.kind](duration=duration, dt=dt, **kwargs)
    except ConfigError as e:
        label = spec if isinstance(spec, str) else format_spec(ps.kind, **ps.params)
        raise ConfigError(f"force profile spec {label!r}: {e}") from None


# ---- seeded sets ----------------------------------------------------------------------------
SET_KINDS = ("mixed", "ramp", "hold", "release", "step")

# Timing of the random shapes, as fractions of the duration D (uniform ranges). Each shape ends
# by 0.9 D at the latest, so every trajectory also shows the branch at (or returning to) a steady
# state; "mixed" alternates ramp and hold.
_RANDOM_TIMING = {
    "ramp": {"start": (0.0, 0.1), "ramp": (0.3, 0.8)},
    "hold": {"start": (0.0, 0.1), "ramp": (0.15, 0.3), "hold": (0.1, 0.25), "release": (0.1, 0.2)},
    "release": {"start": (0.0, 0.1), "ramp": (0.2, 0.4), "release": (0.1, 0.3)},
    "step": {"start": (0.0, 0.2), "rise": (0.05, 0.2)},
}


def _round(x: float, digits: int = 4) -> float:
    """``x`` to ``digits`` significant digits (specs stay short and replay exactly)."""
    return float(f"{x:.{digits}g}")


def _check_peak_range(peak_range) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in peak_range)
    except (TypeError, ValueError):
        raise ConfigError(
            f"peak_range: expected two numbers (low, high) in N, got {peak_range!r}"
        ) from None
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
        raise ConfigError(f"peak_range: expected finite low <= high in N, got ({lo:g}, {hi:g})")
    return lo, hi


def random_specs(
    kind: str = "mixed",
    n: int = 8,
    duration: float = 3.0,
    peak_range: tuple[float, float] = DEFAULT_PEAK_RANGE,
    seed: int | np.random.Generator | None = 0,
) -> list[str]:
    """``n`` spec strings of a varied set, drawn with ``numpy.random.default_rng(seed)``.

    Peaks are uniform in ``peak_range`` (N); start, ramp, hold and release times are uniform
    fractions of ``duration`` (see ``_RANDOM_TIMING``). ``kind="mixed"`` alternates ``ramp`` and
    ``hold`` (so any n >= 2 has both); the other kinds draw that shape only. Values are rounded to
    4 significant digits, so the specs replay exactly with :func:`from_spec`.
    """
    if kind not in SET_KINDS:
        raise ConfigError(f"force profiles: unknown kind '{kind}'; choose one of {list(SET_KINDS)}")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ConfigError(f"force profiles: n must be an integer >= 1, got {n!r}")
    duration = _positive(duration, "duration", "force profiles")
    lo, hi = _check_peak_range(peak_range)
    rng = np.random.default_rng(seed)
    specs = []
    for i in range(int(n)):
        shape = ("ramp", "hold")[i % 2] if kind == "mixed" else kind
        params = {"peak": _round(rng.uniform(lo, hi))}
        for key, (a, b) in _RANDOM_TIMING[shape].items():
            params[key] = _round(rng.uniform(a, b) * duration)
        specs.append(format_spec(shape, **params))
    return specs


def profile_set(
    kind: str = "mixed",
    n: int = 8,
    duration: float = 3.0,
    dt: float = 0.01,
    peak_range: tuple[float, float] = DEFAULT_PEAK_RANGE,
    seed: int | np.random.Generator | None = 0,
) -> np.ndarray:
    """[n, T] N: the profiles of :func:`random_specs` (same arguments) sampled every ``dt`` s."""
    return np.stack(
        [from_spec(s, duration, dt) for s in random_specs(kind, n, duration, peak_range, seed)]
    )
