"""Tests for treeinfer.data.import_bag: synthetic ROS1/ROS2 bags written with rosbags, then
imported."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from treeinfer.cli.import_bag import configure_parser, run_from_args
from treeinfer.data.import_bag import find_pulls, import_bag
from treeinfer.data.trajectories import read_trajectory, read_trajectory_dir
from treeinfer.errors import OutputExistsError, TrajectoryFileError

EPOCH_NS = 1_700_000_000 * 10**9  # header stamps are absolute times
DURATION = 6.5  # s
# Two pulls: (start s, length s, peak force N)
PULLS = [(1.0, 2.0, 10.0), (4.0, 1.5, 6.0)]
COMPLIANCE = 0.005  # m/N: quasi-static branch, displacement = COMPLIANCE * force
Z_REST = 0.8  # m, end-effector height at rest


def force_down(t):
    """Known force on the branch along gravity (N, positive downward)."""
    t = np.asarray(t, dtype=float)
    f = np.zeros_like(t)
    for ts, length, peak in PULLS:
        inside = (t >= ts) & (t <= ts + length)
        f = np.where(inside, peak * np.sin(np.pi * (t - ts) / length) ** 2, f)
    return f


def displacement_down(t):
    """Known displacement of the grasp point (m, positive downward)."""
    return COMPLIANCE * force_down(t)


def _header(ts, store, t_ns, frame):
    """std_msgs/Header at ``t_ns`` (0: an unset stamp, as some drivers publish)."""
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    stamp = Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9)
    extra = {"seq": 0} if store == "ros1" else {}
    return Header(stamp=stamp, frame_id=frame, **extra)


def write_bag(
    path: Path,
    ros: str = "ros2",
    storage: StoragePlugin = StoragePlugin.SQLITE3,
    pose: str = "posestamped",
    force_on_robot: bool = False,
    extra_wrench_topic: bool = False,
    pose_scale: float = 1.0,
    force_scale: float = 1.0,
    tf_frames=("tool0", "elbow"),
    zero_stamps: bool = False,
    t_start: float = 0.0,
) -> Path:
    """Write a bag with a 100 Hz wrench stream and a 50 Hz pose (or /tf) stream.

    Gravity is -z. The wrench carries an irrelevant lateral x component and the
    pose an irrelevant y drift, both of which the projection must remove.
    """
    ts = get_typestore(Stores.ROS1_NOETIC if ros == "ros1" else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in ts.types:  # the Noetic store lacks tf2_msgs
        ts.register(
            get_types_from_msg(
                "geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"
            )
        )
    ser = ts.serialize_ros1 if ros == "ros1" else ts.serialize_cdr
    T = ts.types
    V3, Wrench = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Wrench"]
    WS = T["geometry_msgs/msg/WrenchStamped"]
    Point, Quat, Pose = (
        T["geometry_msgs/msg/Point"],
        T["geometry_msgs/msg/Quaternion"],
        T["geometry_msgs/msg/Pose"],
    )
    PS, TS, TFM = (
        T["geometry_msgs/msg/PoseStamped"],
        T["geometry_msgs/msg/TransformStamped"],
        T["tf2_msgs/msg/TFMessage"],
    )
    Transform = T["geometry_msgs/msg/Transform"]
    q = Quat(x=0.0, y=0.0, z=0.0, w=1.0)

    if ros == "ros1":
        writer = Writer1(path)
    else:
        writer = Writer2(path, version=9, storage_plugin=storage)
    msgs = []  # (t_ns, conn, raw)
    with writer:
        kw = {"typestore": ts}
        c_f = writer.add_connection("/ft_sensor/wrench", "geometry_msgs/msg/WrenchStamped", **kw)
        c_f2 = (
            writer.add_connection("/ft_raw", "geometry_msgs/msg/WrenchStamped", **kw)
            if extra_wrench_topic
            else None
        )
        if pose == "tf":
            c_p = writer.add_connection("/tf", "tf2_msgs/msg/TFMessage", **kw)
            c_static = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", **kw)
        elif pose == "posestamped":
            c_p = writer.add_connection("/ee_pose", "geometry_msgs/msg/PoseStamped", **kw)
        else:  # no pose stream at all
            c_p = None
        c_other = writer.add_connection("/joint_temp", "geometry_msgs/msg/Vector3", **kw)

        sign = -1.0 if force_on_robot else 1.0
        for k, t in enumerate(np.arange(0.003, DURATION, 0.01)):  # 100 Hz, offset grid
            t_ns = EPOCH_NS + round(t * 1e9)
            fz = -force_down(t) * force_scale  # downward force on the branch = -z
            msg = WS(
                header=_header(ts, ros, 0 if zero_stamps else t_ns, "base_link"),
                wrench=Wrench(
                    force=V3(x=0.3 * np.cos(t), y=0.0, z=sign * fz), torque=V3(x=0.0, y=0.0, z=0.0)
                ),
            )
            msgs.append((t_ns, c_f, ser(msg, "geometry_msgs/msg/WrenchStamped")))
            if c_f2 is not None:
                msgs.append((t_ns, c_f2, ser(msg, "geometry_msgs/msg/WrenchStamped")))
        for t in np.arange(0.0, DURATION, 0.02):  # 50 Hz
            t_ns = EPOCH_NS + round(t * 1e9)
            z = (Z_REST - displacement_down(t)) * pose_scale
            y = 0.01 * t
            if c_p is None:
                continue
            if pose == "tf":
                hdr = _header(ts, ros, 0 if zero_stamps else t_ns, "base_link")
                trs = [
                    TS(
                        header=hdr,
                        child_frame_id=tf_frames[0],
                        transform=Transform(translation=V3(x=0.4, y=y, z=z), rotation=q),
                    ),
                ]
                if len(tf_frames) > 1:
                    trs.append(
                        TS(
                            header=hdr,
                            child_frame_id=tf_frames[1],
                            transform=Transform(
                                translation=V3(x=0.1, y=0.0, z=2.0 - t), rotation=q
                            ),
                        )
                    )
                msgs.append((t_ns, c_p, ser(TFM(transforms=trs), "tf2_msgs/msg/TFMessage")))
            else:
                msg = PS(
                    header=_header(ts, ros, 0 if zero_stamps else t_ns, "base_link"),
                    pose=Pose(position=Point(x=0.4, y=y, z=z), orientation=q),
                )
                msgs.append((t_ns, c_p, ser(msg, "geometry_msgs/msg/PoseStamped")))
        msgs.append((EPOCH_NS, c_other, ser(V3(x=1.0, y=2.0, z=3.0), "geometry_msgs/msg/Vector3")))
        if pose == "tf":
            st = TS(
                header=_header(ts, ros, 0 if zero_stamps else EPOCH_NS, "world"),
                child_frame_id="base_link",
                transform=Transform(translation=V3(x=0.0, y=0.0, z=0.0), rotation=q),
            )
            msgs.append((EPOCH_NS, c_static, ser(TFM(transforms=[st]), "tf2_msgs/msg/TFMessage")))
        for t_ns, conn, raw in sorted(msgs, key=lambda m: m[0]):
            if t_ns >= EPOCH_NS + t_start * 1e9:
                writer.write(conn, t_ns, raw)
    return path


def expected_segments(dt=0.01, lead_in=0.25):
    """Independent expectation from the known force: on the grid k*dt from the first
    common sample (t=0.003 s, the first wrench message), each pull runs from the last
    zero-force sample before the ramp (onset) to the first zero-force sample after it,
    preceded by ``lead_in`` of rest. Returns (absolute time of row 0, row count)."""
    grid = 0.003 + dt * np.arange(int((DURATION - 0.02 - 0.003) / dt) + 1)
    segs = []
    for ts, length, _ in PULLS:
        inside = np.flatnonzero((grid > ts) & (grid < ts + length))
        start, stop = inside[0] - 1, inside[-1] + 2
        n_lead = round(lead_in / dt)
        segs.append((grid[start - n_lead], stop - start + n_lead))
    return segs


def provenance(folder):
    return json.loads((Path(folder) / "import.json").read_text())


def check_pulls(paths, dt=0.01):
    assert len(paths) == 2
    assert all(p.is_file() for p in paths)
    for path, (t_abs0, n) in zip(paths, expected_segments(dt)):
        tr = read_trajectory(path)
        assert tr.n_steps == n
        assert tr.time[0] == 0.0 and tr.dt == pytest.approx(dt, rel=1e-9)
        t_abs = t_abs0 + tr.time
        np.testing.assert_allclose(tr.force, force_down(t_abs), atol=0.02)
        np.testing.assert_allclose(tr.displacement, displacement_down(t_abs), atol=1e-4)
        # rest lead-in: displacement zero and force below threshold before the pull
        n_lead = round(0.25 / dt)
        assert np.all(np.abs(tr.displacement[:n_lead]) < 1e-4)
        assert np.all(tr.force[:n_lead] < 0.5)
        assert tr.force.max() > 5.0


# ----------------------------------------------------------------------------- happy paths


def test_ros1_posestamped(tmp_path):
    bag = write_bag(tmp_path / "session.bag", ros="ros1")
    paths = import_bag(bag, tmp_path / "out")
    assert [p.name for p in paths] == ["session_pull001.csv", "session_pull002.csv"]
    assert [p.parent for p in paths] == [tmp_path / "out"] * 2
    check_pulls(paths)
    prov = provenance(tmp_path / "out")
    assert prov["force_topic"] == "/ft_sensor/wrench" and prov["time_source"] == "header"
    assert paths[0].read_text().startswith("time,force,displacement\n")
    assert len(read_trajectory_dir(tmp_path / "out")) == 2


def test_ros2_sqlite_tf_with_child_frame_and_force_sign(tmp_path):
    # wrench published as force on the robot (reaction): force_sign=-1 recovers it
    bag = write_bag(tmp_path / "rec2", pose="tf", force_on_robot=True)
    paths = import_bag(bag, tmp_path / "out", tf_child_frame="/tool0", force_sign=-1)
    check_pulls(paths)
    assert provenance(tmp_path / "out")["tf_child_frame"] == "tool0"


def test_ros2_mcap_posestamped_and_single_tf_frame_autodetect(tmp_path):
    check_pulls(import_bag(write_bag(tmp_path / "m", storage=StoragePlugin.MCAP), tmp_path / "o1"))
    bag = write_bag(tmp_path / "tf1", pose="tf", tf_frames=("tool0",))
    check_pulls(import_bag(bag, tmp_path / "o2"))  # one child frame: no option needed
    bag1 = write_bag(tmp_path / "tf1.bag", ros="ros1", pose="tf")
    check_pulls(import_bag(bag1, tmp_path / "o3", tf_child_frame="tool0"))


def test_other_dt_and_cli(tmp_path):
    bag = write_bag(tmp_path / "a.bag", ros="ros1")
    parser = configure_parser(argparse.ArgumentParser())
    args = parser.parse_args(
        [
            str(bag),
            "--out",
            str(tmp_path / "out"),
            "--dt",
            "0.02",
            "--gravity-axis",
            "0,0,-1",
            "--force-sign",
            "1",
        ]
    )
    check_pulls(run_from_args(args), dt=0.02)


def test_threshold_above_peak_finds_no_pull_with_hint(tmp_path):
    bag = write_bag(tmp_path / "a.bag", ros="ros1")
    with pytest.raises(
        TrajectoryFileError, match="largest |force| .* 10 N, threshold 50 N.*force-sign"
    ):
        import_bag(bag, tmp_path / "out", rest_force_threshold=50.0)
    assert not (tmp_path / "out").exists()


def test_wrong_force_sign_gives_negative_forces(tmp_path):
    bag = write_bag(tmp_path / "a.bag", ros="ros1")
    with pytest.warns(UserWarning, match="opposite directions .*check --force-sign"):
        paths = import_bag(bag, tmp_path / "out", force_sign=-1)
    assert read_trajectory(paths[0]).force.min() < -9.0


def test_zero_header_stamps_use_bag_time_and_recording_starting_mid_pull(tmp_path):
    bag = write_bag(tmp_path / "late.bag", ros="ros1", zero_stamps=True, t_start=1.5)
    with pytest.warns(UserWarning, match="pull 1 starts at the first common sample"):
        paths = import_bag(bag, tmp_path / "out")
    assert len(paths) == 1  # the first pull has no rest pose and is skipped
    assert provenance(tmp_path / "out")["time_source"] == "bag"
    tr = read_trajectory(paths[0])
    t_abs0, n = expected_segments()[1]
    assert tr.n_steps == n
    np.testing.assert_allclose(tr.force, force_down(t_abs0 + tr.time), atol=0.02)


# ----------------------------------------------------------------------------- topic errors


def test_ambiguous_force_topic_lists_candidates(tmp_path):
    bag = write_bag(tmp_path / "amb", extra_wrench_topic=True)
    with pytest.raises(TrajectoryFileError) as exc:
        import_bag(bag, tmp_path / "out")
    msg = str(exc.value)
    assert "several possible force topics" in msg
    assert "/ft_raw [geometry_msgs/msg/WrenchStamped]" in msg and "/ft_sensor/wrench" in msg
    assert "--force-topic" in msg
    check_pulls(import_bag(bag, tmp_path / "out", force_topic="/ft_sensor/wrench"))


def test_missing_pose_topic_lists_topics(tmp_path):
    bag = write_bag(tmp_path / "nopose.bag", ros="ros1", pose="none")
    with pytest.raises(TrajectoryFileError) as exc:
        import_bag(bag, tmp_path / "out")
    msg = str(exc.value)
    assert "nopose.bag" in msg and "no pose topic found" in msg
    assert "/joint_temp [geometry_msgs/msg/Vector3]" in msg
    assert "/ft_sensor/wrench [geometry_msgs/msg/WrenchStamped]" in msg


def test_requested_topic_missing_or_wrong_type(tmp_path):
    bag = write_bag(tmp_path / "b.bag", ros="ros1")
    with pytest.raises(
        TrajectoryFileError, match="pose topic '/nope' is not in the bag; topics found: .*/ee_pose"
    ):
        import_bag(bag, tmp_path / "out", pose_topic="/nope")
    with pytest.raises(
        TrajectoryFileError, match="'/joint_temp' has type geometry_msgs/msg/Vector3"
    ):
        import_bag(bag, tmp_path / "out", force_topic="/joint_temp")


def test_tf_child_frame_ambiguous_or_unknown(tmp_path):
    bag = write_bag(tmp_path / "tf", pose="tf")
    with pytest.raises(
        TrajectoryFileError, match="several child frames: elbow .*tool0.*--tf-child-frame"
    ):
        import_bag(bag, tmp_path / "out")
    with pytest.raises(TrajectoryFileError, match="no transform with child frame 'wrist'"):
        import_bag(bag, tmp_path / "out", tf_child_frame="wrist")


def test_not_a_bag(tmp_path):
    fake = tmp_path / "fake.bag"
    fake.write_bytes(b"not a bag at all")
    with pytest.raises(TrajectoryFileError, match="fake.bag: cannot read"):
        import_bag(fake, tmp_path / "out")
    with pytest.raises(TrajectoryFileError, match="bag not found"):
        import_bag(tmp_path / "missing.bag", tmp_path / "out")
    (tmp_path / "emptydir").mkdir()
    with pytest.raises(TrajectoryFileError, match="cannot read"):
        import_bag(tmp_path / "emptydir", tmp_path / "out")


# ----------------------------------------------------------------------------- output safety


def test_failing_import_leaves_no_output(tmp_path):
    # positions in millimetres: the first pull is written to the staging folder,
    # then the unit check fails; nothing may remain.
    bag = write_bag(tmp_path / "mm.bag", ros="ros1", pose_scale=1000.0)
    with pytest.raises(TrajectoryFileError, match="looks like millimetres"):
        import_bag(bag, tmp_path / "out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mm.bag"]

    # with force=True an existing (treeinfer-written) folder survives a failed import untouched
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.csv").write_text("old")
    (out / ".treeinfer-output").write_text('{"writer": "treeinfer", "complete": true}')
    with pytest.raises(TrajectoryFileError):
        import_bag(bag, out, force=True)
    assert sorted(p.name for p in out.iterdir()) == [".treeinfer-output", "keep.csv"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mm.bag", "out"]


def test_existing_output_refused_unless_force(tmp_path):
    bag = write_bag(tmp_path / "a.bag", ros="ros1")
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.csv").write_text("x")
    with pytest.raises(OutputExistsError):
        import_bag(bag, out)
    # --force replaces only a folder treeinfer wrote (issue 14): a foreign one stays
    with pytest.raises(OutputExistsError, match="replaces only folders treeinfer wrote"):
        import_bag(bag, out, force=True)
    assert [p.name for p in out.iterdir()] == ["old.csv"]
    (out / ".treeinfer-output").write_text('{"writer": "treeinfer", "complete": true}')
    paths = import_bag(bag, out, force=True)
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [p.name for p in paths]
        + [".treeinfer-output", "import.json", "manifest.json", "pulls.yaml"]
    )
    (old,) = tmp_path.glob("out.old-*")  # --force kept the folder it replaced (issue 28)
    assert (old / "old.csv").read_text() == "x"


# ----------------------------------------------------------------------------- pull splitting


def test_find_pulls_ignores_spikes_widens_to_ramp_feet_and_clips_lead_in():
    f = np.zeros(40)
    f[5] = 3.0  # one-sample spike
    f[10:20] = [0.2, 0.5, 2, 2, 2, 2, 2, 2, 0.6, 0.3]  # ramps below the threshold 1.0
    f[20:23] = [0.1, 0.05, 0.4]  # release ends at the minimum 0.05 (index 21)
    f[23:30] = 2.0
    pulls = find_pulls(f, threshold=1.0, min_samples=3, lead_samples=4)
    # first: onset at 9 (f=0 < 0.2), lead 4 samples (the spike inside it is harmless),
    # release through 20 (0.1), 21 (0.05) -> stop 22
    # second: onset walks back from 23 to 22 (0.4 > 0.05 stops it), so no rest sample
    # is left before it (lead == start); release includes the first zero sample (30)
    assert [tuple(p) for p in pulls] == [(5, 9, 22), (22, 22, 31)]
    assert find_pulls(-f, 1.0, 3, 4) == pulls  # |force|
    assert find_pulls(np.full(5, 2.0), 1.0, 3, 2)[0] == (0, 0, 5)  # no rest before
    assert find_pulls(f, threshold=5.0, min_samples=1, lead_samples=4) == []


# ----------------------------------------------------------------------------- real-bag cleaning

REAL_PULLS = [(1.5, 3.0, 8.0), (6.5, 3.0, 5.0)]  # (start s, length s, peak N)
REAL_DURATION = 10.5
OFFSET = 0.8  # N, biased rest force
BLIP = (4.9, 1.2, 0.9)  # a 1.2 s noise blip of 0.9 N above rest


def real_force(t):
    t = np.asarray(t, float)
    f = np.zeros_like(t)
    for ts, length, peak in REAL_PULLS:
        inside = (t >= ts) & (t <= ts + length)
        f = np.where(inside, peak * np.sin(np.pi * (t - ts) / length) ** 2, f)
    return f


def _fill(ts, msgtype, **values):
    """A message of type ``name`` with every field zero/empty except ``values`` (nested too)."""
    import dataclasses

    cls = ts.types[msgtype]
    kw = {}
    for fld in dataclasses.fields(cls):
        if fld.name.startswith("__"):
            continue
        if fld.name in values:
            kw[fld.name] = values[fld.name]
        elif fld.type.startswith("list["):
            kw[fld.name] = []
        elif "__msg__" in fld.type:
            kw[fld.name] = _fill(ts, fld.type.replace("__msg__", "/msg/").replace("__", "/"))
        elif fld.type == "str":
            kw[fld.name] = ""
        else:
            kw[fld.name] = 0
    return cls(**kw)


def write_real_bag(path, ros="ros1", kind="wrench", pose_hz=10.0, sideways=False, on_robot=False):
    """A bag like the real Kinova recordings: pose at ``pose_hz`` (PoseStamped ``/tool_pose``),
    joint states, and the force as ``kind``: "wrench" (WrenchStamped 100 Hz with a rest offset
    and a noise blip), "kortex" (BaseCyclic_Feedback 100 Hz: force and tool pose), or "none"."""
    from treeinfer.data.import_bag import kortex_typestore

    ts = kortex_typestore(ros == "ros1")
    ser = ts.serialize_ros1 if ros == "ros1" else ts.serialize_cdr
    T = ts.types
    axis = np.array([1.0, 0.0, 0.0]) if sideways else np.array([0.0, 0.0, -1.0])
    q = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    writer = Writer1(path) if ros == "ros1" else Writer2(path, version=9)
    msgs = []
    with writer:
        kw = {"typestore": ts}
        c_js = writer.add_connection("/joint_states", "sensor_msgs/msg/JointState", **kw)
        c_pose = writer.add_connection("/tool_pose", "geometry_msgs/msg/PoseStamped", **kw)
        if kind == "wrench":
            c_f = writer.add_connection("/wrench", "geometry_msgs/msg/WrenchStamped", **kw)
        elif kind == "kortex":
            c_f = writer.add_connection(
                "/my_gen3/base_feedback", "kortex_driver/msg/BaseCyclic_Feedback", **kw
            )
        sign = -1.0 if on_robot else 1.0
        for t in np.arange(0.0, REAL_DURATION, 1.0 / pose_hz):
            t_ns = EPOCH_NS + round(t * 1e9)
            p = np.array([0.4, 0.01 * t, Z_REST]) + COMPLIANCE * real_force(t) * axis
            msg = T["geometry_msgs/msg/PoseStamped"](
                header=_header(ts, ros, t_ns, "base_link"),
                pose=T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]), orientation=q
                ),
            )
            msgs.append((t_ns, c_pose, ser(msg, "geometry_msgs/msg/PoseStamped")))
            js = _fill(
                ts,
                "sensor_msgs/msg/JointState",
                header=_header(ts, ros, t_ns, "base_link"),
                name=["j1"],
                position=np.array([0.1]),
                velocity=np.array([0.0]),
                effort=np.array([1.0]),
            )
            msgs.append((t_ns, c_js, ser(js, "sensor_msgs/msg/JointState")))
        for t in np.arange(0.005, REAL_DURATION, 0.01):
            if kind == "none":
                break
            t_ns = EPOCH_NS + round(t * 1e9)
            fmag = real_force(t)
            if kind == "wrench":
                fmag = fmag + OFFSET + (BLIP[2] if BLIP[0] <= t <= BLIP[0] + BLIP[1] else 0.0)
            fv = sign * fmag * axis
            p = np.array([0.4, 0.01 * t, Z_REST]) + COMPLIANCE * real_force(t) * axis
            if kind == "wrench":
                V3 = T["geometry_msgs/msg/Vector3"]
                msg = T["geometry_msgs/msg/WrenchStamped"](
                    header=_header(ts, ros, t_ns, "base_link"),
                    wrench=T["geometry_msgs/msg/Wrench"](
                        force=V3(x=fv[0], y=fv[1], z=fv[2]), torque=V3(x=0.0, y=0.0, z=0.0)
                    ),
                )
                msgs.append((t_ns, c_f, ser(msg, "geometry_msgs/msg/WrenchStamped")))
            else:
                base = _fill(
                    ts,
                    "kortex_driver/msg/BaseFeedback",
                    tool_external_wrench_force_x=fv[0],
                    tool_external_wrench_force_y=fv[1],
                    tool_external_wrench_force_z=fv[2],
                    tool_pose_x=p[0],
                    tool_pose_y=p[1],
                    tool_pose_z=p[2],
                )
                msg = _fill(ts, "kortex_driver/msg/BaseCyclic_Feedback", base=base)
                msgs.append((t_ns, c_f, ser(msg, "kortex_driver/msg/BaseCyclic_Feedback")))
        for t_ns, conn, raw in sorted(msgs, key=lambda m: m[0]):
            writer.write(conn, t_ns, raw)
    return path


def test_real_bag_tare_blip_and_upsampling_notice(tmp_path):
    bag = write_real_bag(tmp_path / "real.bag")
    notes = []
    with pytest.warns(UserWarning) as rec:
        paths = import_bag(bag, tmp_path / "out", notices=notes)
    text = " ".join(str(w.message) for w in rec)
    assert "/tool_pose has one message every 0.1 s" in text and "--dt 0.1" in text
    assert "a blip, skipped" in text
    assert len(paths) == 2
    tare = [n for n in notes if n.startswith("tare")]
    assert tare and "0.8" in tare[0]
    for path, (start, length, peak) in zip(paths, REAL_PULLS):
        tr = read_trajectory(path)
        assert tr.force.max() == pytest.approx(peak, abs=0.02)
        # the onset is found at the foot of the ramp, not 0.4 s late mid-ramp
        assert np.all(tr.force[: round(0.25 / 0.01)] < 0.05)
        onset = tr.time[np.flatnonzero(tr.force > 0.02)[0]]
        assert onset == pytest.approx(0.25 + 0.05, abs=0.03)  # sin^2 ramp passes 0.02 N at 0.05 s
        assert tr.displacement.max() == pytest.approx(COMPLIANCE * peak, rel=0.02)
    assert provenance(tmp_path / "out")["options"]["tare_offset_N"] == pytest.approx(0.8, abs=0.01)
    # dt=None keeps the slower stream's rate: no upsampling notice
    notes2 = []
    paths2 = import_bag(bag, tmp_path / "out2", dt=None, notices=notes2)
    assert read_trajectory(paths2[0]).dt == pytest.approx(0.1, rel=1e-6)
    assert not any("resampling" in n for n in notes2)


def test_real_bag_without_tare_mistakes_the_blip(tmp_path):
    bag = write_real_bag(tmp_path / "real.bag")
    # the 0.8 N offset puts the whole record above the 0.44 N threshold: one "pull" from the
    # first sample, which has no rest before it
    with (
        pytest.warns(UserWarning, match="no rest pose before it"),
        pytest.raises(TrajectoryFileError, match="no pull found"),
    ):
        import_bag(bag, tmp_path / "out", tare=False)


def test_joint_states_only_bag_says_what_is_missing(tmp_path):
    bag = write_real_bag(tmp_path / "js.bag", kind="none")
    with pytest.raises(TrajectoryFileError) as e:
        import_bag(bag, tmp_path / "out")
    msg = str(e.value)
    assert "no force at the end effector" in msg
    assert "joint states/torques (/joint_states)" in msg and "/tool_pose" in msg
    assert "WrenchStamped" in msg and "kortex_driver" in msg
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("ros", ["ros1", "ros2"])
def test_kortex_feedback_as_force_and_pose(tmp_path, ros):
    bag = write_real_bag(
        tmp_path / ("k.bag" if ros == "ros1" else "k2"), ros=ros, kind="kortex", on_robot=True
    )
    paths = import_bag(bag, tmp_path / "out", force_sign=-1)
    prov = provenance(tmp_path / "out")
    assert prov["force_topic"] == "/my_gen3/base_feedback" and prov["time_source"] == "bag"
    assert prov["pose_topic"] == "/my_gen3/base_feedback"
    assert len(paths) == 2
    tr = read_trajectory(paths[0])
    assert tr.force.max() == pytest.approx(REAL_PULLS[0][2], abs=0.02)
    np.testing.assert_allclose(tr.displacement, COMPLIANCE * tr.force, atol=2e-4)
    # the PoseStamped stream may be chosen for the position instead
    paths2 = import_bag(bag, tmp_path / "out2", force_sign=-1, pose_topic="/tool_pose", dt=0.1)
    assert provenance(tmp_path / "out2")["pose_topic"] == "/tool_pose"
    assert read_trajectory(paths2[0]).displacement.max() == pytest.approx(
        COMPLIANCE * REAL_PULLS[0][2], rel=0.03
    )


def test_sideways_pull_projection_distance_and_sidecar(tmp_path):
    from treeinfer.data.pulls import read_pulls

    bag = write_real_bag(tmp_path / "side.bag", kind="kortex", sideways=True)
    paths = import_bag(
        bag, tmp_path / "p", direction=(1, 0, 0), dt=0.05, grasp_branch="b", grasp_fraction=0.5
    )
    tr = read_trajectory(paths[0])
    assert tr.force.max() == pytest.approx(REAL_PULLS[0][2], abs=0.02)
    np.testing.assert_allclose(tr.displacement, COMPLIANCE * tr.force, atol=2e-4)
    side = read_pulls(tmp_path / "p" / "pulls.yaml")
    assert side.pulls[paths[0].name].direction == (1.0, 0.0, 0.0)
    assert side.pulls[paths[0].name].fraction == 0.5
    paths_d = import_bag(bag, tmp_path / "d", direction=(1, 0, 0), dt=0.05, displacement="distance")
    trd = read_trajectory(paths_d[0])
    # distance from the rest pose includes the slow y drift (0.01 m/s) that projection ignores
    assert np.all(trd.displacement >= np.abs(tr.displacement) - 1e-12)
    assert np.all(trd.displacement >= 0)
    with pytest.warns(UserWarning, match="opposite directions"):
        import_bag(bag, tmp_path / "w", direction=(-1, 0, 0), force_axis=(1, 0, 0), dt=0.05)


def test_cli_cleaning_options(tmp_path, capsys):
    from treeinfer.data.pulls import read_pulls

    bag = write_real_bag(tmp_path / "real.bag")
    parser = configure_parser(argparse.ArgumentParser())
    argv = [str(bag), "--out", str(tmp_path / "o"), "--dt", "source", "--grasp-fraction", "0.5"]
    paths = run_from_args(parser.parse_args(argv))
    out = capsys.readouterr().out
    assert "note: tare: subtracted the force at rest, 0.8 N" in out
    assert "a blip, skipped" in out and "resampling" not in out
    assert read_trajectory(paths[0]).dt == pytest.approx(0.1, rel=1e-6)
    assert read_pulls(tmp_path / "o" / "pulls.yaml").pulls[paths[0].name].fraction == 0.5
    argv = [str(bag), "--out", str(tmp_path / "p"), "--no-tare", "--min-peak-fraction", "0"]
    with pytest.raises(TrajectoryFileError, match="no pull found"):
        run_from_args(parser.parse_args(argv))
