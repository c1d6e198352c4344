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
trajectory CSV (:mod:`treeinfer.trajectories`), with the data folder's ``pulls.yaml`` and
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
import struct
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


# ----------------------------------------------------------------------------- Kinova and topics

KORTEX_TYPE = "kortex_driver/msg/BaseCyclic_Feedback"
JOINT_STATE_TYPES = ("sensor_msgs/msg/JointState",)
# The kortex_driver definition (ROS1 full-text form: the type, then each nested type after a
# line of '='), registered with rosbags' typestore so no ROS installation is needed.
KORTEX_MSGDEF = """\
uint32 frame_id
BaseFeedback base
ActuatorFeedback[] actuators
InterconnectCyclic_Feedback interconnect
================================================================================
MSG: kortex_driver/BaseFeedback
uint32 active_state_connection_identifier
uint32 active_state
float32 arm_voltage
float32 arm_current
float32 temperature_cpu
float32 temperature_ambient
float32 imu_acceleration_x
float32 imu_acceleration_y
float32 imu_acceleration_z
float32 imu_angular_velocity_x
float32 imu_angular_velocity_y
float32 imu_angular_velocity_z
float32 tool_pose_x
float32 tool_pose_y
float32 tool_pose_z
float32 tool_pose_theta_x
float32 tool_pose_theta_y
float32 tool_pose_theta_z
float32 tool_twist_linear_x
float32 tool_twist_linear_y
float32 tool_twist_linear_z
float32 tool_twist_angular_x
float32 tool_twist_angular_y
float32 tool_twist_angular_z
float32 tool_external_wrench_force_x
float32 tool_external_wrench_force_y
float32 tool_external_wrench_force_z
float32 tool_external_wrench_torque_x
float32 tool_external_wrench_torque_y
float32 tool_external_wrench_torque_z
uint32 fault_bank_a
uint32 fault_bank_b
uint32 warning_bank_a
uint32 warning_bank_b
float32 commanded_tool_pose_x
float32 commanded_tool_pose_y
float32 commanded_tool_pose_z
float32 commanded_tool_pose_theta_x
float32 commanded_tool_pose_theta_y
float32 commanded_tool_pose_theta_z
================================================================================
MSG: kortex_driver/ActuatorFeedback
uint32 command_id
uint32 status_flags
uint32 jitter_comm
float32 position
float32 velocity
float32 torque
float32 current_motor
float32 voltage
float32 temperature_motor
float32 temperature_core
uint32 fault_bank_a
uint32 fault_bank_b
uint32 warning_bank_a
uint32 warning_bank_b
================================================================================
MSG: kortex_driver/InterconnectCyclic_Feedback
InterconnectCyclic_MessageId feedback_id
uint32 status_flags
uint32 jitter_comm
float32 imu_acceleration_x
float32 imu_acceleration_y
float32 imu_acceleration_z
float32 imu_angular_velocity_x
float32 imu_angular_velocity_y
float32 imu_angular_velocity_z
float32 voltage
float32 temperature_core
uint32 fault_bank_a
uint32 fault_bank_b
uint32 warning_bank_a
uint32 warning_bank_b
InterconnectCyclic_Feedback_tool_feedback oneof_tool_feedback
================================================================================
MSG: kortex_driver/InterconnectCyclic_MessageId
uint32 identifier
================================================================================
MSG: kortex_driver/InterconnectCyclic_Feedback_tool_feedback
GripperCyclic_Feedback[] gripper_feedback
================================================================================
MSG: kortex_driver/GripperCyclic_Feedback
GripperCyclic_MessageId feedback_id
uint32 status_flags
uint32 fault_bank_a
uint32 fault_bank_b
uint32 warning_bank_a
uint32 warning_bank_b
MotorFeedback[] motor
================================================================================
MSG: kortex_driver/GripperCyclic_MessageId
uint32 identifier
================================================================================
MSG: kortex_driver/MotorFeedback
uint32 motor_id
float32 position
float32 velocity
float32 current_motor
float32 voltage
float32 temperature_motor
"""


def kortex_typestore(ros1: bool):
    """A rosbags typestore (Noetic for ROS1, Humble for ROS2) with the ``kortex_driver``
    feedback types registered from :data:`KORTEX_MSGDEF` (a fixed, known definition)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    ts.register(get_types_from_msg(KORTEX_MSGDEF, KORTEX_TYPE))
    return ts


def bag_topics(bag_path: str | os.PathLike) -> dict[str, str]:
    """Topic -> message type of a bag (reads the index only, no messages).

    Raises:
        TrajectoryFileError: missing or unreadable bag.
    """
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.rosbag1 import ReaderError as ReaderError1
    from rosbags.rosbag2 import ReaderError as ReaderError2

    bag = Path(bag_path)
    if not bag.exists():
        raise TrajectoryFileError(f"{bag}: bag not found")
    try:
        reader = AnyReader([bag], default_typestore=kortex_typestore(False))
        reader.open()
    except (AnyReaderError, ReaderError1, ReaderError2, FileNotFoundError, OSError) as e:
        raise TrajectoryFileError(f"{bag}: cannot read as a ROS1 or ROS2 bag ({e})") from None
    try:
        return {name: info.msgtype for name, info in reader.topics.items()}
    finally:
        reader.close()


def missing_force_message(bag: Path, topics: dict[str, str]) -> str | None:
    """If the bag has no force source, say what it has and what is missing; else ``None``."""
    if any(m in FORCE_TYPES or m == KORTEX_TYPE for m in topics.values()):
        return None
    listing = ", ".join(f"{t} [{m}]" for t, m in sorted(topics.items())) or "(no topics)"
    joints = [t for t, m in sorted(topics.items()) if m in JOINT_STATE_TYPES]
    poses = [t for t, m in sorted(topics.items()) if m in POSE_TYPES]
    have = []
    if joints:
        have.append(f"joint states/torques ({', '.join(joints)})")
    if poses:
        have.append(f"end-effector poses ({', '.join(poses)})")
    return (
        f"{bag}: no force at the end effector: the bag has "
        + (" and ".join(have) if have else "no usable stream")
        + f" but no wrench topic (topics found: {listing}). treeinfer needs the force applied "
        "on the branch: record a geometry_msgs/WrenchStamped topic (a wrist force/torque "
        "sensor, or the arm driver's estimated external wrench), or on a Kinova arm the "
        f"kortex_driver feedback topic (e.g. /my_gen3/base_feedback, {KORTEX_TYPE}), whose "
        "tool_external_wrench is used. Estimating the tool force from joint torques needs the "
        "arm's kinematic and dynamic model, which treeinfer does not have."
    )


def read_kortex_streams(
    bag_path: str | os.PathLike,
    feedback_topic: str | None = None,
    pose_topic: str | None = None,
) -> BagStreams:
    """Force and tool position from a Kinova ``kortex_driver/BaseCyclic_Feedback`` topic.

    Force: ``base.tool_external_wrench_force_{x,y,z}`` (N); position: ``base.tool_pose_{x,y,z}``
    (m, base frame), or a ``PoseStamped``/``TransformStamped`` ``pose_topic`` if given. The
    feedback message has no header: times are the bag's record times for both streams.

    Raises:
        TrajectoryFileError: missing topic, undecodable message, fewer than 2 messages.
    """
    from rosbags.highlevel import AnyReader, AnyReaderError

    bag = Path(bag_path)
    topics = bag_topics(bag)
    cands = [t for t, m in sorted(topics.items()) if m == KORTEX_TYPE]
    if feedback_topic is None:
        if len(cands) != 1:
            raise TrajectoryFileError(
                f"{bag}: {'several' if cands else 'no'} {KORTEX_TYPE} topics"
                + (f" ({', '.join(cands)}); choose one with --force-topic" if cands else "")
            )
        feedback_topic = cands[0]
    elif topics.get(feedback_topic) != KORTEX_TYPE:
        raise TrajectoryFileError(
            f"{bag}: topic '{feedback_topic}' is not a {KORTEX_TYPE} topic "
            f"(it is {topics.get(feedback_topic, 'missing')})"
        )
    if pose_topic is not None and topics.get(pose_topic) not in (
        "geometry_msgs/msg/PoseStamped",
        "geometry_msgs/msg/TransformStamped",
        KORTEX_TYPE,
    ):
        raise TrajectoryFileError(
            f"{bag}: pose topic '{pose_topic}' has type {topics.get(pose_topic, '(missing)')}; "
            f"expected PoseStamped, TransformStamped or {KORTEX_TYPE}"
        )
    pose_topic = pose_topic or feedback_topic
    reader = AnyReader([bag], default_typestore=kortex_typestore(False))
    reader.open()
    ts = kortex_typestore(not reader.is2)
    decode = ts.deserialize_cdr if reader.is2 else ts.deserialize_ros1
    f_t, f_v, p_t, p_v = [], [], [], []
    try:
        conns = [c for c in reader.connections if c.topic in (feedback_topic, pose_topic)]
        for conn, t_bag, raw in reader.messages(connections=conns):
            try:
                msg = decode(raw, conn.msgtype)
            except (ValueError, IndexError, KeyError, TypeError, struct.error) as e:
                raise TrajectoryFileError(
                    f"{bag}: cannot decode a message on {conn.topic} ({e})"
                ) from None
            if conn.topic == feedback_topic:
                b = msg.base
                f_t.append(t_bag)
                f_v.append(
                    (
                        b.tool_external_wrench_force_x,
                        b.tool_external_wrench_force_y,
                        b.tool_external_wrench_force_z,
                    )
                )
            if conn.topic == pose_topic:
                p_t.append(t_bag)
                if conn.msgtype == KORTEX_TYPE:
                    b = msg.base
                    p_v.append((b.tool_pose_x, b.tool_pose_y, b.tool_pose_z))
                elif conn.msgtype == "geometry_msgs/msg/TransformStamped":
                    p_v.append(_xyz(msg.transform.translation))
                else:
                    p_v.append(_xyz(msg.pose.position))
    except AnyReaderError as e:
        raise TrajectoryFileError(f"{bag}: cannot read messages ({e})") from None
    finally:
        reader.close()
    for name, topic, vals in (("force", feedback_topic, f_v), ("pose", pose_topic, p_v)):
        if len(vals) < 2:
            raise TrajectoryFileError(
                f"{bag}: {name} topic {topic} has {len(vals)} usable message(s); at least 2 needed"
            )
    ft, fv = _sorted_unique(np.asarray(f_t, np.int64), np.asarray(f_v, float))
    pt, pv = _sorted_unique(np.asarray(p_t, np.int64), np.asarray(p_v, float))
    origin = int(min(ft[0], pt[0]))
    return BagStreams(
        (ft - origin) * 1e-9,
        fv,
        (pt - origin) * 1e-9,
        pv,
        origin,
        feedback_topic,
        pose_topic,
        "",
        "bag",
    )


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
    :mod:`treeinfer.pulls`) and ``import.json`` (source, topics, options, notices).

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
