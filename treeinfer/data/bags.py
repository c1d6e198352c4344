"""Reading the raw force and pose streams of a ROS1/ROS2 bag, resampling them, and finding the
pulls in them (the first steps of :func:`treeinfer.data.import_bag.import_bag`)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..errors import ConfigError, TrajectoryFileError

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

    from .bag_messages import open_bag_reader

    bag = Path(bag_path)
    if not bag.exists():
        raise TrajectoryFileError(f"{bag}: bag not found")
    # Types come only from rosbags' built-in stores, never from the bag's own definitions
    # (rosbags would turn those into Python code): see treeinfer.data.bag_messages.
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
    """Linear interpolation of ``values [N, D]`` at times ``time [N]`` onto ``grid [G]``.

    Returns ``[G, D]``."""
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
