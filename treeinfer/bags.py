"""Import pulls from a ROS bag (``treeinfer import-bag``).

Reads a ROS1 ``.bag`` file or a ROS2 bag (folder with ``metadata.yaml``, sqlite3
or mcap storage, or a bare ``.db3``/``.mcap`` file) with the ``rosbags``
package, so no ROS installation is needed. Two streams are used:

* force: ``geometry_msgs/msg/WrenchStamped`` or ``geometry_msgs/msg/Wrench``;
* end-effector position: ``geometry_msgs/msg/PoseStamped``,
  ``geometry_msgs/msg/TransformStamped`` or ``tf2_msgs/msg/TFMessage`` (one
  child frame, chosen with ``tf_child_frame``).

Both are resampled (linear interpolation) to a fixed step over their common
time span, projected on the gravity axis (positive = downward), and cut into
pulls; each pull becomes one trajectory CSV (:mod:`treeinfer.trajectories`).

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
from typing import NamedTuple

import numpy as np

from ._io import check_output_dir, staged_output_dir
from .errors import ConfigError, TrajectoryFileError
from .trajectories import Trajectory, write_trajectory

__all__ = [
    "FORCE_TYPES",
    "POSE_TYPES",
    "BagStreams",
    "Pull",
    "find_pulls",
    "import_bag",
    "read_bag_streams",
    "resample",
]

FORCE_TYPES = ("geometry_msgs/msg/WrenchStamped", "geometry_msgs/msg/Wrench")
POSE_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/TransformStamped",
    "tf2_msgs/msg/TFMessage",
)
TF_TYPE = "tf2_msgs/msg/TFMessage"
STATIC_TF_TOPICS = ("/tf_static", "tf_static")  # static transforms cannot carry a pull

DEFAULT_THRESHOLD_FRACTION = 0.05  # of the largest |force| in the bag
DEFAULT_THRESHOLD_MIN = 0.2  # N


class BagStreams(NamedTuple):
    """Raw force and position streams read from a bag.

    Attributes:
        force_time: [N] seconds since ``origin_ns``, increasing.
        force: [N, 3] newtons, as published (wrench frame).
        pose_time: [M] seconds since ``origin_ns``, increasing.
        position: [M, 3] metres, in the pose's (fixed) frame.
        origin_ns: absolute time of 0 s, nanoseconds (header or bag clock).
        force_topic, pose_topic: topics used.
        pose_frame: the TF child frame used ('' for pose topics).
        time_source: 'header' or 'bag'.
    """

    force_time: np.ndarray
    force: np.ndarray
    pose_time: np.ndarray
    position: np.ndarray
    origin_ns: int
    force_topic: str
    pose_topic: str
    pose_frame: str
    time_source: str


class Pull(NamedTuple):
    """Sample indices of one pull on the resampled grid: rest lead-in ``[lead, start)``,
    pull from onset to release ``[start, stop)`` (see :func:`find_pulls`)."""

    lead: int
    start: int
    stop: int


# ----------------------------------------------------------------------------- reading


def _select_topic(
    topics: dict[str, str | None],
    requested: str | None,
    allowed: Sequence[str],
    kind: str,
    option: str,
    bag: Path,
) -> str:
    listing = ", ".join(f"{t} [{m}]" for t, m in sorted(topics.items())) or "(no topics)"
    if requested is not None:
        if requested not in topics:
            raise TrajectoryFileError(
                f"{bag}: {kind} topic '{requested}' is not in the bag; topics found: {listing}"
            )
        if topics[requested] not in allowed:
            raise TrajectoryFileError(
                f"{bag}: {kind} topic '{requested}' has type {topics[requested]}, expected one of "
                f"{', '.join(allowed)}"
            )
        return requested
    cands = [t for t, m in sorted(topics.items()) if m in allowed and t not in STATIC_TF_TOPICS]
    if len(cands) == 1:
        return cands[0]
    if not cands:
        raise TrajectoryFileError(
            f"{bag}: no {kind} topic found (types {', '.join(allowed)}); topics found: {listing}"
        )
    listed = ", ".join(f"{t} [{topics[t]}]" for t in cands)
    raise TrajectoryFileError(
        f"{bag}: several possible {kind} topics: {listed}; choose one with {option}"
    )


def _stamp_ns(msg) -> int:
    header = getattr(msg, "header", None)
    if header is None:
        return 0
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _xyz(v) -> tuple[float, float, float]:
    return (float(v.x), float(v.y), float(v.z))


def _norm_frame(name: str) -> str:
    return name.lstrip("/")


def _sorted_unique(t_ns: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sort by time; of several samples at one instant keep the last received."""
    order = np.argsort(t_ns, kind="stable")
    t_ns, values = t_ns[order], values[order]
    keep = np.append(t_ns[1:] != t_ns[:-1], True)
    return t_ns[keep], values[keep]


def read_bag_streams(
    bag_path: str | os.PathLike,
    force_topic: str | None = None,
    pose_topic: str | None = None,
    tf_child_frame: str | None = None,
) -> BagStreams:
    """Read the force and position streams of a bag (topics auto-detected by type if not given).

    Raises:
        TrajectoryFileError: unreadable bag, missing/ambiguous topics or TF frames,
            or streams with fewer than 2 messages.
    """
    from rosbags.highlevel import AnyReaderError

    from .bag_types import open_bag_reader

    bag = Path(bag_path)
    if not bag.exists():
        raise TrajectoryFileError(f"{bag}: bag not found")
    # Types come only from rosbags' built-in stores, never from the bag's own definitions
    # (rosbags would turn those into Python code): see treeinfer.bag_types.
    reader = open_bag_reader(bag)
    try:
        topics = {name: info.msgtype for name, info in reader.topics.items()}
        ftopic = _select_topic(topics, force_topic, FORCE_TYPES, "force", "--force-topic", bag)
        ptopic = _select_topic(topics, pose_topic, POSE_TYPES, "pose", "--pose-topic", bag)
        want = {ftopic, ptopic}
        conns = [c for c in reader.connections if c.topic in want]

        f_hdr, f_bag, f_val = [], [], []
        p_hdr, p_bag, p_val = [], [], []
        tf_frames: dict[str, set[str]] = {}  # child -> parents seen
        child = None if tf_child_frame is None else _norm_frame(tf_child_frame)
        tf_samples: list[tuple[str, str, int, int, tuple[float, float, float]]] = []
        for conn, t_bag, raw in reader.messages(connections=conns):
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except AnyReaderError as e:
                raise TrajectoryFileError(
                    f"{bag}: cannot decode a message on {conn.topic} ({e})"
                ) from None
            if conn.topic == ftopic:
                wrench = msg.wrench if hasattr(msg, "wrench") else msg
                f_hdr.append(_stamp_ns(msg))
                f_bag.append(t_bag)
                f_val.append(_xyz(wrench.force))
            if conn.topic == ptopic:
                if conn.msgtype == TF_TYPE:
                    for tr in msg.transforms:
                        c, p = _norm_frame(tr.child_frame_id), _norm_frame(tr.header.frame_id)
                        tf_frames.setdefault(c, set()).add(p)
                        tf_samples.append(
                            (c, p, _stamp_ns(tr), t_bag, _xyz(tr.transform.translation))
                        )
                elif conn.msgtype == "geometry_msgs/msg/TransformStamped":
                    p_hdr.append(_stamp_ns(msg))
                    p_bag.append(t_bag)
                    p_val.append(_xyz(msg.transform.translation))
                else:
                    p_hdr.append(_stamp_ns(msg))
                    p_bag.append(t_bag)
                    p_val.append(_xyz(msg.pose.position))
    finally:
        reader.close()

    frame = ""
    if topics[ptopic] == TF_TYPE:
        frames = ", ".join(
            f"{c} (parent {', '.join(sorted(p))})" for c, p in sorted(tf_frames.items())
        )
        if child is None:
            if len(tf_frames) != 1:
                raise TrajectoryFileError(
                    f"{bag}: topic {ptopic} holds transforms for several child frames: "
                    f"{frames or '(none)'}; choose the end-effector frame with --tf-child-frame"
                )
            child = next(iter(tf_frames))
        if child not in tf_frames:
            raise TrajectoryFileError(
                f"{bag}: no transform with child frame '{child}' on {ptopic}; "
                f"child frames found: {frames or '(none)'}"
            )
        if len(tf_frames[child]) > 1:
            raise TrajectoryFileError(
                f"{bag}: child frame '{child}' on {ptopic} has several parent frames "
                f"({', '.join(sorted(tf_frames[child]))}); TF chains are not composed"
            )
        frame = child
        for c, _, hdr, t_bag, xyz in tf_samples:
            if c == child:
                p_hdr.append(hdr)
                p_bag.append(t_bag)
                p_val.append(xyz)

    for name, topic, vals in (("force", ftopic, f_val), ("pose", ptopic, p_val)):
        if len(vals) < 2:
            raise TrajectoryFileError(
                f"{bag}: {name} topic {topic} has {len(vals)} usable message(s); at least 2 needed"
            )
    use_header = all(h > 0 for h in f_hdr) and all(h > 0 for h in p_hdr)
    f_t = np.asarray(f_hdr if use_header else f_bag, dtype=np.int64)
    p_t = np.asarray(p_hdr if use_header else p_bag, dtype=np.int64)
    f_t, f_v = _sorted_unique(f_t, np.asarray(f_val, dtype=float))
    p_t, p_v = _sorted_unique(p_t, np.asarray(p_val, dtype=float))
    origin = int(min(f_t[0], p_t[0]))
    return BagStreams(
        force_time=(f_t - origin) * 1e-9,
        force=f_v,
        pose_time=(p_t - origin) * 1e-9,
        position=p_v,
        origin_ns=origin,
        force_topic=ftopic,
        pose_topic=ptopic,
        pose_frame=frame,
        time_source="header" if use_header else "bag",
    )


# ----------------------------------------------------------------------------- processing


def resample(time: np.ndarray, values: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Linear interpolation of ``values [N, D]`` at times ``time [N]`` onto ``grid [G]`` -> [G, D]."""
    return np.stack([np.interp(grid, time, values[:, j]) for j in range(values.shape[1])], axis=1)


def find_pulls(
    force: np.ndarray, threshold: float, min_samples: int, lead_samples: int
) -> list[Pull]:
    """Find pulls in a force record on a uniform grid.

    A pull is a run of at least ``min_samples`` samples with ``|force| > threshold``,
    widened to the foot of its ramps: backwards while ``|force|`` keeps decreasing
    (the onset, where the robot started to pull) and forwards likewise (the release).
    Without this the rest pose would be taken on the rising ramp, already displaced.

    Args:
        force: [G] newtons on the uniform grid.
        threshold: newtons.
        min_samples: shorter runs (noise spikes) are ignored.
        lead_samples: rest samples wanted before each onset (fewer if the previous
            pull or the recording start is closer).

    Returns:
        Pulls in time order; ``lead == start`` means no rest sample precedes it.
    """
    a = np.abs(np.asarray(force, dtype=float))
    edges = np.diff(np.concatenate([[0], (a > threshold).astype(np.int8), [0]]))
    runs = [
        (int(s), int(e))
        for s, e in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1))
        if e - s >= min_samples
    ]
    pulls: list[Pull] = []
    prev_stop = 0
    for k, (s, e) in enumerate(runs):
        next_start = runs[k + 1][0] if k + 1 < len(runs) else a.shape[0]
        while s > prev_stop and a[s - 1] < a[s]:
            s -= 1
        while e < next_start and a[e] < a[e - 1]:
            e += 1
        pulls.append(Pull(max(prev_stop, s - lead_samples), s, e))
        prev_stop = e
    return pulls


def _unit(v, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.linalg.norm(a) == 0:
        raise ConfigError(f"{name} must be three finite numbers, not all zero; got {v!r}")
    return a / np.linalg.norm(a)


def import_bag(
    bag_path: str | os.PathLike,
    out_dir: str | os.PathLike,
    force_topic: str | None = None,
    pose_topic: str | None = None,
    dt: float = 0.01,
    gravity_axis: Sequence[float] = (0.0, 0.0, -1.0),
    rest_force_threshold: float | None = None,
    min_pull_duration: float = 0.2,
    force: bool = False,
    *,
    tf_child_frame: str | None = None,
    force_sign: int = 1,
    force_axis: Sequence[float] | None = None,
    lead_in: float = 0.25,
) -> list[Path]:
    """Cut a bag into pulls and write one trajectory CSV per pull into ``out_dir``.

    Args:
        bag_path: ROS1 ``.bag`` file or ROS2 bag folder (or ``.db3``/``.mcap`` file).
        out_dir: output folder, written all at once (nothing is left on error).
        force_topic, pose_topic: topics; auto-detected by message type if ``None``.
        dt: output time step, seconds.
        gravity_axis: direction of gravity in the pose frame (default -z).
        rest_force_threshold: newtons; a pull is where |force| exceeds it. Default:
            5% of the largest |force| in the bag or 0.2 N, whichever is larger.
        min_pull_duration: seconds; shorter excursions above the threshold are ignored.
        force: replace a non-empty ``out_dir``.
        tf_child_frame: end-effector frame when the pose comes from ``/tf``.
        force_sign: +1 if the reading is the force applied on the branch, -1 if it
            is the force on the robot.
        force_axis: direction of gravity in the wrench frame (default ``gravity_axis``).
        lead_in: seconds of rest kept before each pull's onset; the rest pose
            (displacement 0) is the mean position over it.

    Returns:
        Paths of the written CSVs inside ``out_dir``, in time order.

    Raises:
        TrajectoryFileError: unreadable bag, topic problems, no pulls, implausible values.
        ConfigError: invalid option values.
        OutputExistsError: ``out_dir`` holds files and ``force`` is False.
    """
    if not (dt > 0 and np.isfinite(dt)):
        raise ConfigError(f"dt must be a positive number of seconds, got {dt!r}")
    if force_sign not in (1, -1):
        raise ConfigError(f"force_sign must be +1 or -1, got {force_sign!r}")
    if rest_force_threshold is not None and not rest_force_threshold > 0:
        raise ConfigError(f"rest_force_threshold must be > 0 N, got {rest_force_threshold!r}")
    if not min_pull_duration >= 0 or not lead_in >= 0:
        raise ConfigError("min_pull_duration and lead_in must be >= 0 seconds")
    g_pose = _unit(gravity_axis, "gravity_axis")
    g_force = g_pose if force_axis is None else _unit(force_axis, "force_axis")

    bag = Path(bag_path)
    check_output_dir(out_dir, force=force, what="import-bag output")  # fail before reading
    s = read_bag_streams(bag, force_topic, pose_topic, tf_child_frame)
    t0 = max(s.force_time[0], s.pose_time[0])
    t1 = min(s.force_time[-1], s.pose_time[-1])
    n = int(np.floor((t1 - t0) / dt + 1e-9)) + 1 if t1 > t0 else 0
    if n < 3:
        raise TrajectoryFileError(
            f"{bag}: force ({s.force_topic}) and pose ({s.pose_topic}) overlap for "
            f"{max(t1 - t0, 0.0):g} s only; too short for dt={dt:g} s"
        )
    grid = t0 + dt * np.arange(n)
    f = force_sign * resample(s.force_time, s.force, grid) @ g_force  # [G] N, + = downward
    x = resample(s.pose_time, s.position, grid) @ g_pose  # [G] m, + = downward

    fmax = float(np.max(np.abs(f)))
    thr = (
        rest_force_threshold
        if rest_force_threshold is not None
        else max(DEFAULT_THRESHOLD_FRACTION * fmax, DEFAULT_THRESHOLD_MIN)
    )
    min_samples = max(2, int(np.ceil(min_pull_duration / dt - 1e-9)))
    lead_samples = max(1, round(lead_in / dt))
    pulls = find_pulls(f, thr, min_samples, lead_samples)

    kept: list[Pull] = []
    for k, p in enumerate(pulls):
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
            f"{bag}: no pull found on {s.force_topic}: largest |force| along gravity is "
            f"{fmax:.3g} N, threshold {thr:.3g} N, minimum duration {min_pull_duration:g} s "
            "(check --force-sign/--gravity-axis or lower --rest-force-threshold)"
        )

    stem = bag.stem if bag.is_file() else bag.name
    written: list[Path] = []
    out_dir = Path(out_dir)
    with staged_output_dir(out_dir, force=force, what="import-bag output") as stage:
        for k, p in enumerate(kept, start=1):
            rest = float(np.mean(x[p.lead : p.start]))
            name = f"{stem}_pull{k:03d}.csv"
            traj = Trajectory(
                time=dt * np.arange(p.stop - p.lead),
                force=f[p.lead : p.stop].copy(),
                displacement=x[p.lead : p.stop] - rest,
                velocity=None,
                source=f"{bag.name}:{name}",
            )
            abs_start = s.origin_ns * 1e-9 + grid[p.lead]
            comments = [
                f"imported from {bag.name} by treeinfer import-bag",
                (
                    f"force_topic={s.force_topic} force_sign={force_sign:+d} "
                    f"force_axis={g_force.tolist()}"
                ),
                f"pose_topic={s.pose_topic}"
                + (f" tf_child_frame={s.pose_frame}" if s.pose_frame else "")
                + f" gravity_axis={g_pose.tolist()}",
                f"time_source={s.time_source} start_time={abs_start:.9f} dt={dt:g}",
                f"threshold={thr:.6g} N lead_in_samples={p.start - p.lead}",
            ]
            write_trajectory(stage / name, traj, comments)
            written.append(out_dir / name)
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
