"""Import pulls from a ROS bag (``treeinfer import-bag``).

Reads a ROS1 ``.bag`` file or a ROS2 bag (folder with ``metadata.yaml``, sqlite3
or mcap storage, or a bare ``.db3``/``.mcap`` file) with the ``rosbags``
package, so no ROS installation is needed. Two streams are used:

* force: ``geometry_msgs/msg/WrenchStamped`` or ``geometry_msgs/msg/Wrench``;
* end-effector position: ``geometry_msgs/msg/PoseStamped``,
  ``geometry_msgs/msg/TransformStamped`` or ``tf2_msgs/msg/TFMessage`` (one
  child frame, chosen with ``tf_child_frame``).

A Kinova ``kortex_driver/msg/BaseCyclic_Feedback`` topic can serve as both: its
``base.tool_external_wrench_force_*`` and ``base.tool_pose_*`` fields (the type is registered
from a built-in definition). A bag with joint states/torques but no force stream is refused
with a message naming what it has and what is missing.

Both are resampled (linear interpolation) to a fixed step over their common
time span (a notice when that is far above a stream's own rate), the force is tared (its rest
level removed), both are projected on the pull direction (default: the gravity axis, positive
= downward; the displacement may instead be the distance from the rest pose), and the record
is cut into pulls (blips far below the largest pull are dropped); each pull becomes one
trajectory CSV (:mod:`treeinfer.data.trajectories`), with the data folder's ``pulls.yaml`` and
``import.json``. Force and displacement should rise together; a pull where they do not gets
a warning (usually a wrong ``force_sign``).

Assumptions, stated once here:

* The force reading, times ``force_sign``, is the force the robot applies **on
  the branch**. Many arms publish the external wrench acting *on the robot*
  (the reaction); pass ``force_sign=-1`` for those.
* The wrench is expressed in a frame whose orientation matches the pose frame
  (e.g. the base frame); if not, give ``force_axis``: the direction of gravity
  in the wrench's frame (constant, so the wrench frame must not rotate much).
* The pose (or TF transform) is expressed in a fixed frame (world/base) in
  which ``gravity_axis`` points down. TF chains are not composed.
* Times are the message header stamps when every message of both streams has
  a non-zero stamp, else the bag's record times (for both, never mixed).
"""

from __future__ import annotations

import argparse
import os
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..errors import ConfigError, TrajectoryFileError
from ..io.atomic import check_output_dir, staged_output_dir
from .bags import (  # noqa: F401 -- re-exported: the old import path keeps working
    DEFAULT_THRESHOLD_FRACTION,
    DEFAULT_THRESHOLD_MIN,
    FORCE_TYPES,
    POSE_TYPES,
    STATIC_TF_TOPICS,
    TF_TYPE,
    BagStreams,
    Pull,
    _unit,
    find_pulls,
    read_bag_streams,
    resample,
)
from .kortex import (  # noqa: F401 -- re-exported: the old import path keeps working
    JOINT_STATE_TYPES,
    KORTEX_MSGDEF,
    KORTEX_TYPE,
    bag_topics,
    kortex_typestore,
    missing_force_message,
    read_kortex_streams,
)
from .trajectories import Trajectory, write_trajectory

__all__ = [
    "FORCE_TYPES",
    "KORTEX_TYPE",
    "POSE_TYPES",
    "BagStreams",
    "Pull",
    "bag_topics",
    "find_pulls",
    "import_bag",
    "kortex_typestore",
    "missing_force_message",
    "read_bag_streams",
    "read_kortex_streams",
    "resample",
    "rest_level",
    "sign_agreement",
]


# ----------------------------------------------------------------------------- cleaning


DISPLACEMENT_KINDS = ("projection", "distance")
MAX_UPSAMPLE = 2.0  # resampling more than this many times above a source rate gets a notice
MIN_PEAK_FRACTION = 0.2  # pulls peaking below this share of the largest are noise blips


def source_interval(t: np.ndarray) -> float:
    """Median interval [s] between messages of a stream (its typical sample period)."""
    d = np.diff(np.asarray(t, float))
    return float(np.median(d)) if d.size else float("nan")


def rest_level(f: np.ndarray, share: float = 0.3) -> float:
    """The force at rest [N]: the median of the densest ``share`` of the samples.

    The rest level is the most common value of a recording that rests between pulls; the
    narrowest window holding ``share`` of the sorted samples finds it without a threshold
    (a half-sample-mode estimate), so an offset as large as the pulls themselves is found."""
    s = np.sort(np.asarray(f, float))
    k = max(2, int(np.ceil(share * s.size)))
    if s.size <= k:
        return float(np.median(s))
    widths = s[k - 1 :] - s[: s.size - k + 1]
    i = int(np.argmin(widths))
    return float(np.median(s[i : i + k]))


def sign_agreement(force: np.ndarray, displacement: np.ndarray) -> float:
    """Correlation of force and displacement over a pull (should be positive; NaN if flat)."""
    f, x = np.asarray(force, float), np.asarray(displacement, float)
    if f.size < 3 or np.std(f) == 0 or np.std(x) == 0:
        return float("nan")
    return float(np.corrcoef(f, x)[0, 1])


def _notify(notices: list[str], msg: str, warn: bool = False) -> None:
    notices.append(msg)
    if warn:
        warnings.warn(msg, stacklevel=3)


def import_bag(
    bag_path: str | os.PathLike,
    out_dir: str | os.PathLike,
    force_topic: str | None = None,
    pose_topic: str | None = None,
    dt: float | None = 0.01,
    gravity_axis: Sequence[float] = (0.0, 0.0, -1.0),
    rest_force_threshold: float | None = None,
    min_pull_duration: float = 0.2,
    force: bool = False,
    *,
    tf_child_frame: str | None = None,
    force_sign: int = 1,
    force_axis: Sequence[float] | None = None,
    lead_in: float = 0.25,
    tare: bool = True,
    min_peak_fraction: float = MIN_PEAK_FRACTION,
    max_upsample: float | None = MAX_UPSAMPLE,
    displacement: str = "projection",
    direction: Sequence[float] | None = None,
    grasp_branch: str | None = None,
    grasp_fraction: float | None = None,
    grasp_distance: float | None = None,
    notices: list[str] | None = None,
) -> list[Path]:
    """Cut a bag into pulls and write one trajectory CSV per pull into ``out_dir``.

    Also writes ``pulls.yaml`` (grasp point and direction of every pull, see
    :mod:`treeinfer.data.pulls`) and ``import.json`` (source, topics, options, notices).

    Args:
        bag_path: ROS1 ``.bag`` file or ROS2 bag folder (or ``.db3``/``.mcap`` file).
        out_dir: output folder, written all at once (nothing is left on error).
        force_topic, pose_topic: topics; auto-detected by message type if ``None``. A Kinova
            ``kortex_driver/BaseCyclic_Feedback`` topic serves as force source (its tool
            external wrench) and, unless ``pose_topic`` names another, as pose source.
        dt: output time step, seconds; ``None``: the slower stream's own interval (no
            upsampling).
        gravity_axis: direction of gravity in the pose frame (default -z).
        rest_force_threshold: newtons above the rest level; a pull is where |force| exceeds
            it. Default: 5% of the largest |force| or 0.2 N, whichever is larger.
        min_pull_duration: seconds; shorter excursions above the threshold are ignored.
        force: replace a non-empty ``out_dir``.
        tf_child_frame: end-effector frame when the pose comes from ``/tf``.
        force_sign: +1 if the reading is the force applied on the branch, -1 if it is the force
            on the robot (as the Kinova external wrench and most arm drivers publish).
        force_axis: the pull direction in the wrench frame (default: the pull direction, i.e.
            the wrench frame is aligned with the pose frame).
        lead_in: seconds of rest kept before each pull's onset; the rest pose is the mean
            position over it.
        tare: subtract the force at rest (:func:`rest_level`) before finding pulls.
        min_peak_fraction: pulls whose peak |force| is below this share of the largest pull's
            are dropped as noise blips (with a notice).
        max_upsample: a notice when ``dt`` is more than this many times finer than a source
            stream's interval (linear interpolation invents the samples between); ``None``: off.
        displacement: ``"projection"`` (on the pull direction, signed) or ``"distance"``
            (Euclidean distance from the rest pose, >= 0; for pulls of unknown direction).
        direction: the pull direction in the pose frame (default: ``gravity_axis``, a
            downward pull). Force and displacement are both projected on it.
        grasp_branch, grasp_fraction, grasp_distance: grasp point written to ``pulls.yaml``.
        notices: if a list, every notice (tare, resampling, dropped blips, sign) is appended.

    Returns:
        Paths of the written CSVs inside ``out_dir``, in time order.

    Raises:
        TrajectoryFileError: unreadable bag, no force source (the message says what the bag
            has and what is missing), topic problems, no pulls, implausible values.
        ConfigError: invalid option values.
        OutputExistsError: ``out_dir`` holds files and ``force`` is False.
    """
    from .pulls import PULLS_FILE, PullSpec, write_pulls
    from .trajectories import write_provenance

    notes: list[str] = [] if notices is None else notices
    if dt is not None and not (dt > 0 and np.isfinite(dt)):
        raise ConfigError(f"dt must be a positive number of seconds, got {dt!r}")
    if force_sign not in (1, -1):
        raise ConfigError(f"force_sign must be +1 or -1, got {force_sign!r}")
    if rest_force_threshold is not None and not rest_force_threshold > 0:
        raise ConfigError(f"rest_force_threshold must be > 0 N, got {rest_force_threshold!r}")
    if not min_pull_duration >= 0 or not lead_in >= 0:
        raise ConfigError("min_pull_duration and lead_in must be >= 0 seconds")
    if displacement not in DISPLACEMENT_KINDS:
        raise ConfigError(
            f"displacement must be one of {', '.join(DISPLACEMENT_KINDS)}, got {displacement!r}"
        )
    if not 0 <= min_peak_fraction < 1:
        raise ConfigError(f"min_peak_fraction must be in [0, 1), got {min_peak_fraction!r}")
    if grasp_fraction is not None and grasp_distance is not None:
        raise ConfigError("give grasp_fraction or grasp_distance, not both")
    g_pose = _unit(gravity_axis, "gravity_axis")
    d_pose = g_pose if direction is None else _unit(direction, "direction")
    d_force = d_pose if force_axis is None else _unit(force_axis, "force_axis")
    sidecar_dir = "down" if direction is None or np.allclose(d_pose, g_pose) else d_pose
    spec = PullSpec(
        grasp_branch,
        grasp_fraction,
        grasp_distance,
        sidecar_dir if isinstance(sidecar_dir, str) else tuple(float(v) for v in sidecar_dir),
    )

    bag = Path(bag_path)
    check_output_dir(out_dir, force=force, what="import-bag output")  # fail before reading
    topics = bag_topics(bag)
    missing = missing_force_message(bag, topics)
    if missing is not None:
        raise TrajectoryFileError(missing)
    has_wrench = any(m in FORCE_TYPES for m in topics.values())
    use_kortex = (force_topic is not None and topics.get(force_topic) == KORTEX_TYPE) or (
        force_topic is None and not has_wrench
    )
    if use_kortex:
        s = read_kortex_streams(bag, force_topic, pose_topic)
    else:
        s = read_bag_streams(bag, force_topic, pose_topic, tf_child_frame)

    f_int, p_int = source_interval(s.force_time), source_interval(s.pose_time)
    if dt is None:
        dt = max(f_int, p_int)
        _notify(notes, f"dt = {dt:.4g} s, the slower stream's message interval (no upsampling)")
    for name, topic, iv in (("force", s.force_topic, f_int), ("pose", s.pose_topic, p_int)):
        if max_upsample is not None and np.isfinite(iv) and iv > max_upsample * dt * (1 + 1e-6):
            _notify(
                notes,
                f"{bag}: the {name} stream {topic} has one message every {iv:.3g} s "
                f"({1 / iv:.3g} Hz); resampling it to dt={dt:g} s is {iv / dt:.0f}x its rate, the "
                "samples in between are linear interpolation, not measurements; "
                f"pass dt={iv:.3g} (--dt {iv:.3g}) or "
                "dt=None (--dt source) to keep the measured rate",
                warn=True,
            )
    t0 = max(s.force_time[0], s.pose_time[0])
    t1 = min(s.force_time[-1], s.pose_time[-1])
    n = int(np.floor((t1 - t0) / dt + 1e-9)) + 1 if t1 > t0 else 0
    if n < 3:
        raise TrajectoryFileError(
            f"{bag}: force ({s.force_topic}) and pose ({s.pose_topic}) overlap for "
            f"{max(t1 - t0, 0.0):g} s only; too short for dt={dt:g} s"
        )
    grid = t0 + dt * np.arange(n)
    f = force_sign * resample(s.force_time, s.force, grid) @ d_force  # [G] N along the pull
    pos = resample(s.pose_time, s.position, grid)  # [G, 3] m

    offset = 0.0
    if tare:
        offset = rest_level(f)
        f = f - offset
        _notify(notes, f"tare: subtracted the force at rest, {offset:.4g} N")
    fmax = float(np.max(np.abs(f)))
    thr = (
        rest_force_threshold
        if rest_force_threshold is not None
        else max(DEFAULT_THRESHOLD_FRACTION * fmax, DEFAULT_THRESHOLD_MIN)
    )
    min_samples = max(2, int(np.ceil(min_pull_duration / dt - 1e-9)))
    lead_samples = max(1, round(lead_in / dt))
    pulls = find_pulls(f, thr, min_samples, lead_samples)
    peaks = [float(np.max(np.abs(f[p.start : p.stop]))) for p in pulls]
    top = max(peaks, default=0.0)

    kept: list[Pull] = []
    prev_stop = 0
    for k, (p, peak) in enumerate(zip(pulls, peaks)):
        if peak < min_peak_fraction * top:
            _notify(
                notes,
                f"{bag}: excursion {k + 1} at t={grid[p.start]:.3f} s peaks at {peak:.3g} N, "
                f"below {min_peak_fraction:.0%} of the largest pull ({top:.3g} N): a blip, skipped",
                warn=True,
            )
            continue
        # a skipped blip just before must not shorten this pull's rest lead-in
        lead = p.lead if p.lead == p.start else max(prev_stop, p.start - lead_samples, 0)
        p = Pull(min(lead, p.start), p.start, p.stop)
        prev_stop = p.stop
        if p.lead == p.start:
            warnings.warn(
                f"{bag}: pull {k + 1} starts at the first common sample (t={grid[p.start]:.3f} s); "
                "no rest pose before it, skipped",
                stacklevel=2,
            )
            continue
        if p.stop == n:
            warnings.warn(
                f"{bag}: pull {k + 1} is still under way when the recording ends; kept as is",
                stacklevel=2,
            )
        kept.append(p)
    if not kept:
        raise TrajectoryFileError(
            f"{bag}: no pull found on {s.force_topic}: largest |force| along the pull is "
            f"{fmax:.3g} N, threshold {thr:.3g} N, minimum duration {min_pull_duration:g} s "
            "(check --force-sign/--gravity-axis or lower --rest-force-threshold)"
        )

    stem = bag.stem if bag.is_file() else bag.name
    written: list[Path] = []
    files: dict[str, dict] = {}
    out_dir = Path(out_dir)
    with staged_output_dir(out_dir, force=force, what="import-bag output") as stage:
        for k, p in enumerate(kept, start=1):
            rest = np.mean(pos[p.lead : p.start], axis=0)
            if displacement == "projection":
                x = (pos[p.lead : p.stop] - rest) @ d_pose
            else:
                x = np.linalg.norm(pos[p.lead : p.stop] - rest, axis=1)
            name = f"{stem}_pull{k:03d}.csv"
            fk = f[p.lead : p.stop].copy()
            r = sign_agreement(fk, x)
            if r < 0:
                _notify(
                    notes,
                    f"{bag}: {name}: force and displacement move in opposite directions "
                    f"(correlation {r:.2f}); check --force-sign (the reading may be the force "
                    "on the robot) and --gravity-axis/--direction",
                    warn=True,
                )
            traj = Trajectory(
                time=dt * np.arange(p.stop - p.lead),
                force=fk,
                displacement=x,
                velocity=None,
                source=f"{bag.name}:{name}",
            )
            write_trajectory(stage / name, traj)
            written.append(out_dir / name)
            files[name] = {
                "start_time": s.origin_ns * 1e-9 + float(grid[p.lead]),
                "lead_in_samples": int(p.start - p.lead),
                "peak_force": float(np.max(np.abs(fk))),
            }
        write_pulls(
            stage / PULLS_FILE,
            {name: spec for name in files},
            header=f"grasp point and pull direction per pull (import-bag {bag.name})",
        )
        write_provenance(
            stage,
            {
                "tool": "treeinfer import-bag",
                "source": bag.name,
                "force_topic": s.force_topic,
                "pose_topic": s.pose_topic,
                "tf_child_frame": s.pose_frame,
                "time_source": s.time_source,
                "options": {
                    "dt": dt,
                    "force_sign": force_sign,
                    "force_axis": d_force.tolist(),
                    "gravity_axis": g_pose.tolist(),
                    "direction": d_pose.tolist(),
                    "displacement": displacement,
                    "tare": tare,
                    "tare_offset_N": offset,
                    "threshold_N": thr,
                    "min_pull_duration": min_pull_duration,
                    "lead_in": lead_in,
                    "min_peak_fraction": min_peak_fraction,
                },
                "source_intervals_s": {"force": f_int, "pose": p_int},
                "notices": list(notes),
                "files": files,
            },
        )
    return written


# ----------------------------------------------------------------------------- CLI


def _triple(text: str) -> tuple[float, float, float]:
    parts = text.replace(",", " ").split()
    try:
        vals = tuple(float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected three numbers like '0,0,-1', got {text!r}")
    if len(vals) != 3:
        raise argparse.ArgumentTypeError(f"expected three numbers like '0,0,-1', got {text!r}")
    return vals  # type: ignore[return-value]
