"""Kinova ``kortex_driver`` feedback as a force source, and the topic listing of a bag (which
force source it has, and what it lacks when it has none)."""

from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np

from ..errors import TrajectoryFileError
from .bags import FORCE_TYPES, POSE_TYPES, BagStreams, _sorted_unique, _xyz

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
    from ..io.safe_load import refuse_special_paths

    refuse_special_paths(bag, "bag", TrajectoryFileError)  # a FIFO would block the reader
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
