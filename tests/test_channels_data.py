"""Observation channels in the data folder (issue 30): channels.yaml, channel files, units,
time offsets and the errors that name the file and field."""

import numpy as np
import pytest
import yaml

import treeinfer as ti
from treeinfer.data.channels import read_channels, sample_weights
from treeinfer.errors import ConfigError, TrajectoryFileError


@pytest.fixture(scope="module")
def tree():
    return ti.load_tree(ti.example_path("two_branch"))


def _folder(tmp_path, entry: dict, rows: str = None):
    tmp_path.mkdir(parents=True, exist_ok=True)
    t = np.arange(101) * 0.02
    force = np.minimum(t, 1.0) * 4.0
    ti.write_trajectory(tmp_path / "pull_a.csv", ti.Trajectory(t, force, 1e-3 * force))
    (tmp_path / "channels").mkdir(exist_ok=True)
    if rows is None:  # 50 Hz marker in mm, on a clock 0.5 s ahead of the pull's
        tc = 0.5 + np.arange(0, 60) * 0.02
        rows = "time,x,z\n" + "".join(f"{a:.3f},{2 * a:.3f},{-a:.3f}\n" for a in tc)
    (tmp_path / "channels" / "m.csv").write_text(rows)
    base = {
        "name": "marker",
        "recording": "pull_a.csv",
        "file": "channels/m.csv",
        "kind": "position",
        "point": {"link": "child", "fraction": 0.5},
        "components": ["x", "z"],
        "units": {"time": "s", "value": "mm"},
        "time_offset": -0.5,
        "noise": 0.5,
    }
    base.update(entry)
    base = {k: v for k, v in base.items() if v is not None}
    (tmp_path / "channels.yaml").write_text(yaml.safe_dump({"channels": [base]}))
    return tmp_path


def test_reads_channel_in_si_on_the_pull_clock(tmp_path, tree):
    folder = _folder(tmp_path, {})
    trajs = ti.read_trajectory_dir(folder)
    assert len(trajs) == 1  # the channel file is not read as a pull
    (ch,) = read_channels(folder, tree, trajs)
    assert ch.kind == "position" and ch.components == ("x", "z")
    np.testing.assert_allclose(ch.time[0], 0.0, atol=1e-12)
    np.testing.assert_allclose(ch.values[:, 0], 2e-3 * (ch.time + 0.5))
    assert ch.noise == pytest.approx(5e-4)
    assert ch.rate == pytest.approx(50.0)
    assert ch.dropped == 0


def test_angle_channel_degrees_and_distance(tmp_path, tree):
    rows = "time,y\n" + "".join(f"{k * 0.01:.2f},{0.1 * k:.3f}\n" for k in range(300))
    folder = _folder(
        tmp_path,
        {
            "kind": "angle",
            "components": ["y"],
            "units": {"value": "deg"},
            "point": {"link": "parent", "distance": 0.4},
            "time_offset": 0.0,
            "noise": "auto",
        },
        rows,
    )
    (ch,) = read_channels(folder, tree, ti.read_trajectory_dir(folder))
    assert ch.noise is None and ch.point.fraction_of(0.8) == pytest.approx(0.5)
    assert ch.dropped == 300 - 201  # samples after the pull's 2 s end
    np.testing.assert_allclose(ch.values[-1, 0], np.radians(20.0))


@pytest.mark.parametrize(
    "entry, match",
    [
        ({"point": {"link": "twig", "fraction": 0.5}}, r"field 'point'.link: unknown point 'twig'"),
        ({"point": {"link": "child", "distance": 0.9}}, "past the end of link 'child'"),
        ({"units": {"value": "deg"}}, r"inconsistent units.*'deg' is a unit of angle"),
        ({"units": {"value": "m"}, "noise": None}, "inconsistent units"),  # mm values read as m?
        ({"time_offset": 30.0}, "no overlap in time with the pull pull_a.csv"),
        ({"recording": "pull_b.csv"}, "no pull 'pull_b.csv'"),
        ({"file": "m.csv"}, "top level"),
        ({"kind": "force"}, "field 'kind'"),
    ],
)
def test_bad_channels_name_file_and_field(tmp_path, tree, entry, match):
    if entry.get("units", {}).get("value") == "m":  # values in mm written as metres: 118 "m"
        rows = "time,x,z\n" + "".join(f"{k * 0.02:.2f},{k * 2.0},{0}\n" for k in range(60))
        folder = _folder(tmp_path, entry, rows)
    else:
        folder = _folder(tmp_path, entry)
    trajs = ti.read_trajectory_dir(folder)
    if entry.get("file") == "m.csv":  # (a top-level CSV would be read as a pull)
        (tmp_path / "m.csv").write_text("time,x,z\n0,0,0\n")
    with pytest.raises(ConfigError, match=match) as e:
        read_channels(folder, tree, trajs)
    assert "channels" in str(e.value)


def test_bad_channel_file_names_line_and_column(tmp_path, tree):
    folder = _folder(tmp_path, {}, "time,x,z\n0,1,2\n0.02,oops,3\n")
    with pytest.raises(TrajectoryFileError, match=r"m.csv, line 3, column 'x'"):
        read_channels(folder, tree, ti.read_trajectory_dir(folder))
    folder = _folder(tmp_path, {}, "time,x\n0,1\n0.02,3\n")
    with pytest.raises(TrajectoryFileError, match=r"missing column\(s\) \['z'\]"):
        read_channels(folder, tree, ti.read_trajectory_dir(folder))


def test_write_read_roundtrip(tmp_path, tree):
    folder = _folder(tmp_path, {})
    trajs = ti.read_trajectory_dir(folder)
    chans = read_channels(folder, tree, trajs)
    out = tmp_path / "copy"
    out.mkdir()
    for tr in trajs:
        ti.write_trajectory(out / tr.source, tr)
    ti.data.write_channels(out, chans)
    (back,) = read_channels(out, tree, ti.read_trajectory_dir(out))
    np.testing.assert_allclose(back.values, chans[0].values, rtol=1e-8)
    np.testing.assert_allclose(back.time, chans[0].time, atol=1e-9)
    assert back.noise == pytest.approx(chans[0].noise)


def test_sample_weights_interpolate():
    grid = np.arange(11) * 0.1
    i, w = sample_weights([0.0, 0.05, 0.97, 1.0], 0.0, 0.1, 11)
    x = grid**2
    np.testing.assert_allclose((1 - w) * x[i] + w * x[i + 1], [0.0, 0.005, 0.943, 1.0], atol=1e-12)


def test_cli_infer_refuses_bad_channel_with_exit_2(tmp_path, capsys):
    from treeinfer.cli import main

    folder = _folder(tmp_path / "data", {"point": {"link": "twig", "fraction": 0.5}})
    rc = main(
        ["infer", "--tree", str(ti.example_path("two_branch")), "--data", str(folder), "--out",
         str(tmp_path / "run")]
    )  # fmt: skip
    assert rc == 2
    err = capsys.readouterr().err
    assert "channels.yaml: channel 'marker': field 'point'.link: unknown point 'twig'" in err
    assert not (tmp_path / "run").exists()


def test_image_channel_with_camera(tmp_path, tree):
    cam = {"focal": [800, 800], "center": [640, 360], "position": [0.5, -2.0, 1.3],
           "rotation": [[1, 0, 0], [0, 0, -1], [0, 1, 0]]}  # fmt: skip
    rows = "time,u,v\n" + "".join(f"{k * 0.04:.2f},{k},{-k}\n" for k in range(40))
    entry = {"kind": "image", "components": ["u", "v"], "units": {"value": "px"}, "camera": cam,
             "time_offset": 0.0, "noise": 1.5}  # fmt: skip
    folder = _folder(tmp_path, entry, rows)
    (ch,) = read_channels(folder, tree, ti.read_trajectory_dir(folder))
    assert ch.kind == "image" and list(ch.axes) == [0, 1] and len(ch.camera) == 16
    assert ch.noise == 1.5
    out = tmp_path / "copy"
    out.mkdir()
    for tr in ti.read_trajectory_dir(folder):
        ti.write_trajectory(out / tr.source, tr)
    ti.data.write_channels(out, (ch,))
    (back,) = read_channels(out, tree, ti.read_trajectory_dir(out))
    assert back.camera == pytest.approx(ch.camera)
    bad = dict(entry, camera={**cam, "rotation": [[1, 0, 0], [0, 1, 0], [0, 1, 0]]})
    with pytest.raises(ConfigError, match=r"field 'camera'.rotation: must be a rotation"):
        read_channels(_folder(tmp_path, bad, rows), tree)
    with pytest.raises(ConfigError, match="needs a camera"):
        read_channels(_folder(tmp_path, dict(entry, camera=None), rows), tree)
    with pytest.raises(ConfigError, match="only image channels have a camera"):
        read_channels(_folder(tmp_path, {"camera": cam}), tree)


def test_channel_files_are_checksummed_for_resume(tmp_path, tree):
    from treeinfer.data.channel_files import channel_manifest
    from treeinfer.io.provenance import data_manifest
    from treeinfer.runs.inputs import check_data_unchanged

    folder = _folder(tmp_path, {})
    man = channel_manifest(folder)
    assert [m["name"] for m in man] == ["channels.yaml", "channels/m.csv"]
    config = {"data": {"dir": str(folder), "files": data_manifest(folder), "channel_files": man}}
    assert len(check_data_unchanged(config)) == 1
    with open(folder / "channels" / "m.csv", "a") as f:
        f.write("9.9,1,1\n")
    with pytest.raises(ConfigError, match=r"changed: channels/m.csv"):
        check_data_unchanged(config)


def test_a_kfold_split_keeps_the_channels_of_its_pulls(tmp_path, tree):
    folder = _folder(tmp_path, {})
    trajs = ti.read_trajectory_dir(folder)
    other = trajs[0]._replace(source="pull_b.csv")
    assert read_channels(folder, tree, [other], only_these_pulls=True) == ()
    with pytest.raises(ConfigError, match="no pull 'pull_a.csv'"):
        read_channels(folder, tree, [other])
    assert len(read_channels(folder, tree, trajs, only_these_pulls=True)) == 1


def test_sensor_name_round_trips_and_is_checked(tmp_path, tree):
    folder = _folder(tmp_path, {"sensor": "cam1"})
    (ch,) = read_channels(folder, tree, ti.read_trajectory_dir(folder))
    assert ch.sensor == "cam1"
    out = tmp_path / "copy"
    out.mkdir()
    for tr in ti.read_trajectory_dir(folder):
        ti.write_trajectory(out / tr.source, tr)
    ti.data.write_channels(out, (ch,))
    assert read_channels(out, tree)[0].sensor == "cam1"
    with pytest.raises(ConfigError, match="field 'sensor'"):
        read_channels(_folder(tmp_path, {"sensor": "a[1]"}), tree)
