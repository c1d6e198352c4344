"""The .pul importer (treeinfer.data.pul, pull_test, import_pul; ``treeinfer import-pul``) on tiny
fixtures written here: a known signed tilt along a known axis comes back in radians with the
right sign, gaps are not interpolated, repeated readings are dropped, and malformed files are
refused with the file, line and field named (exit 2)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from treeinfer.cli.main import main
from treeinfer.data import make_pull_test, read_pul, read_pull_test, read_test_setups
from treeinfer.data.import_pul import import_pul
from treeinfer.errors import OutputExistsError, TrajectoryFileError

TREES_HEADER = (
    "tree_id,tree_species,site,height,circ,sling_height_test_tree,sling_height_anchor_tree,"
    "dist_test_to_anchor,azi_test_from_anchor,height_root_clino,height_trunk_clino,"
    "height_crown_centre,trunk_lean_angle,trunk_lean_dir,root_clino_id,pul_file,notes"
)
TREES_ROW = '7,rs,halloran,6.0,"40.0, 20.0",2.0,0.4,8.0,100,1.0,2.5,4.0,vertical,,2,tiny,a note'
AXIS_ROOT = np.array([0.6, 0.8])  # the direction of the loaded tilt in (X, Y) of inclino2
AXIS_TRUNK = np.array([-1.0, 0.0])
TARE_ROOT, TARE_TRUNK = (0.05, -0.01), (-0.08, 0.03)
DEG_PER_N_ROOT, DEG_PER_N_TRUNK = 5e-4, 1e-3  # tilt per newton of cable force


def _stamp(t: float) -> str:
    """ISO 8601 with 7 decimals and +10:00, as the logger writes (t s after 15:05:00)."""
    whole = int(t)
    frac = f"{t - whole:.7f}"[1:]
    return f"2023-05-03T15:{5 + whole // 60:02d}:{whole % 60:02d}{frac}+10:00"


def force_profile(n: int = 60) -> np.ndarray:
    """kN: rest 10, ramp 20 to 1 kN, hold 10, release 10, rest 10."""
    return np.concatenate(
        [np.zeros(10), np.linspace(0.05, 1.0, 20), np.full(10, 1.0), np.linspace(0.9, 0.0, 10),
         np.zeros(n - 50)]
    )  # fmt: skip


def make_pul(path: Path, gap=None, repeat_at=None, f_kn=None) -> dict:
    """A pretty-printed .pul file (one key per line, so a cycle has a line of its own): a
    0.1 s polling cycle; tilt = force x gain along the axes above, plus the tares."""
    f_kn = force_profile() if f_kn is None else f_kn
    cycles = []
    for i, f in enumerate(f_kn):
        t = 0.1 * i
        c = {
            "force": {
                "val": f * 101.9534,
                "raw": f"{'-' if f < 0 else ' '}   {abs(f):.2f}N\u0003\u0002",
                "timestamp": _stamp(t + 0.02),
            }
        }
        for key, axis, gain, tare in (
            ("inclino2", AXIS_ROOT, DEG_PER_N_ROOT, TARE_ROOT),
            ("inclino", AXIS_TRUNK, DEG_PER_N_TRUNK, TARE_TRUNK),
        ):
            if gap is not None and key == "inclino2" and gap[0] <= i < gap[1]:
                continue
            ti = t + 0.05
            if repeat_at is not None and key == "inclino2" and i == repeat_at:
                ti, xy = t - 0.05, np.asarray(tare) + axis * gain * 1000 * f_kn[i - 1]
            else:
                xy = np.asarray(tare) + axis * gain * 1000 * f
            c[key] = {
                "val": 0.0,
                "raw": f"X={xy[0]:+07.3f}\r\nY={xy[1]:+07.3f}",
                "timestamp": _stamp(ti),
            }
        c["dlen"] = {"val1": 1.0, "val2": 1.0, "raw": "[03507,03665]", "timestamp": _stamp(t)}
        cycles.append(c)
    d = {
        "name": path.stem,
        "inclino_tara": f"{TARE_TRUNK[0]};{TARE_TRUNK[1]}",
        "inclino2_tara": f"{TARE_ROOT[0]};{TARE_ROOT[1]}",
        "force_tara": "0",
        "dlen_tara": "3506.00;3664.00",
        "data": cycles,
    }
    path.write_text(json.dumps(d, indent=1))
    return d


@pytest.fixture
def tiny(tmp_path):
    folder = tmp_path / "mangrove"
    (folder / "pull_tests").mkdir(parents=True)
    (folder / "trees.csv").write_text(TREES_HEADER + "\n" + TREES_ROW + "\n")
    pul = folder / "pull_tests" / "tiny.pul"
    make_pul(pul)
    return pul


def test_reads_raw_channels_tares_and_timestamps(tiny):
    p = read_pul(tiny)
    assert p.n_cycles == 60 and p.force.n == 60
    assert set(p.inclinometers) == {"inclino", "inclino2"}
    assert p.tares["inclino2"] == TARE_ROOT and p.tares["force"] == (0.0,)
    np.testing.assert_allclose(p.force.values, np.round(force_profile(), 2))
    assert np.diff(p.force.t) == pytest.approx(np.full(59, 0.1), abs=1e-6)  # 7 decimals kept


def test_signed_tilt_along_the_loaded_axis(tiny):
    setup = read_test_setups(tiny.parent.parent / "trees.csv")["tiny"]
    assert setup.dbh == pytest.approx(0.40 / math.pi)
    assert setup.cable_angle == pytest.approx(math.atan(1.6 / 8.0))
    assert setup.pull_azimuth_deg == 280 and setup.trunk_lean_deg == 90
    t = make_pull_test(read_pul(tiny), setup)
    np.testing.assert_allclose(t.channels["root"].axis, AXIS_ROOT, atol=2e-3)
    np.testing.assert_allclose(t.channels["trunk"].axis, AXIS_TRUNK, atol=2e-3)
    f = np.round(force_profile(), 2) * 1000
    np.testing.assert_allclose(t.force, f)
    # the readings are 0.03 s after the force's: the interpolated tilt lags by that much
    for ch, gain in (("root", DEG_PER_N_ROOT), ("trunk", DEG_PER_N_TRUNK)):
        want = np.deg2rad(gain * f)
        ok = np.isfinite(t.tilt[ch])
        assert ok[1:].all()
        np.testing.assert_allclose(t.tilt[ch][ok], want[ok], atol=np.deg2rad(gain * 1000) * 0.04)
        assert np.nanmax(t.tilt[ch]) == pytest.approx(np.deg2rad(gain * 1000), rel=0.01)
    ph = t.phases
    assert ph["ramp_start"] == 9 and ph["ramp_end"] == 29
    # the last sample at >= 75% of the peak (0.8 kN), the first back at rest (0 kN)
    assert ph["release_start"] == 41 and ph["release_end"] == 49


def test_gaps_are_not_interpolated_and_repeats_dropped(tmp_path, tiny):
    setup = read_test_setups(tiny.parent.parent / "trees.csv")["tiny"]
    pul = tmp_path / "tiny.pul"
    make_pul(pul, gap=(20, 35))  # 1.5 s without root readings: longer than max_gap (1 s)
    t = make_pull_test(read_pul(pul), setup)
    missing = np.isnan(t.tilt["root"])
    assert missing[21:35].all() and not missing[36:].any()
    t_long = make_pull_test(read_pul(pul), setup, max_gap=5.0)
    assert not np.isnan(t_long.tilt["root"][1:]).any()
    make_pul(pul, repeat_at=25)  # a reading re-reported out of order is dropped, not averaged
    t_rep = make_pull_test(read_pul(pul), setup)
    assert np.isfinite(t_rep.tilt["root"][1:]).all()


def test_tare_is_the_median_at_rest_before_a_sudden_load(tmp_path, tiny):
    """A load applied in one step: the pre-load is every sample before it, not the first."""
    setup = read_test_setups(tiny.parent.parent / "trees.csv")["tiny"]
    rest = np.tile([-0.01, 0.01, 0.01, 0.01], 3)[:11]  # median +0.01 kN, first -0.01 kN
    f = np.concatenate([rest, np.full(30, 1.0), np.zeros(19)])
    pul = tmp_path / "tiny.pul"
    make_pul(pul, f_kn=f)
    t = make_pull_test(read_pul(pul), setup)
    assert t.force[:11] == pytest.approx((rest - 0.01) * 1000)
    assert "tare +10.0 N" in t.steps[1]


def _break(path: Path, cycle: int, key: str, value) -> int:
    """Replace one field of one cycle; return the line of that cycle's opening brace."""
    d = json.loads(path.read_text())
    sensor, field = key.split(".")
    d["data"][cycle][sensor][field] = value
    text = json.dumps(d, indent=1)
    path.write_text(text)
    # the line of the cycle: json.dumps(indent=1) puts each cycle's "{" on a line of its own
    lines = text.splitlines()
    starts = [i + 1 for i, s in enumerate(lines) if s == "  {"]
    return starts[cycle]


@pytest.mark.parametrize(
    "key, value, what",
    [
        ("inclino.raw", "X=+00.02\r\nZ=1", "X=<deg>"),
        ("force.raw", "  abc", "force reading"),
        ("force.timestamp", "yesterday", "ISO 8601"),
        ("dlen.raw", "[1;2]", "[n1,n2]"),
    ],
)
def test_malformed_fields_name_file_line_and_field(tiny, key, value, what):
    line = _break(tiny, 13, key, value)
    with pytest.raises(TrajectoryFileError) as e:
        read_pul(tiny)
    msg = str(e.value)
    assert str(tiny) in msg and f"line {line}" in msg and f"data[13].{key}" in msg and what in msg


def test_malformed_json_and_structure(tiny, tmp_path):
    text = tiny.read_text().splitlines()
    text[7] = text[7] + ","  # a stray comma on line 8: not JSON
    bad = tmp_path / "bad.pul"
    bad.write_text("\n".join(text))
    with pytest.raises(TrajectoryFileError, match=r"bad\.pul, line 8, column \d+: not valid JSON"):
        read_pul(bad)
    bad.write_text('{"name": "x", "data": []}')
    with pytest.raises(TrajectoryFileError, match="empty list of cycles"):
        read_pul(bad)
    d = json.loads(tiny.read_text())
    del d["inclino2_tara"]
    bad.write_text(json.dumps(d))
    with pytest.raises(TrajectoryFileError, match="inclino2_tara.*missing"):
        read_pul(bad)


def test_metadata_errors_name_line_and_column(tmp_path):
    p = tmp_path / "trees.csv"
    p.write_text(TREES_HEADER + "\n" + TREES_ROW.replace(",2.0,0.4,", ",two,0.4,") + "\n")
    with pytest.raises(TrajectoryFileError, match=r"line 2, field 'sling_height_test_tree'"):
        read_test_setups(p)
    p.write_text("a,b\n1,2\n")
    with pytest.raises(TrajectoryFileError, match="missing column"):
        read_test_setups(p)


def test_import_writes_csv_and_json_and_round_trips(tiny, tmp_path):
    out = tmp_path / "data"
    res = import_pul([tiny], out)
    assert sorted(p.name for p in res.paths) == ["tiny.csv", "tiny.json"]
    back = read_pull_test(out / "tiny.json")
    t = res.tests[0]
    np.testing.assert_allclose(back.force, t.force)
    np.testing.assert_allclose(back.tilt["root"], t.tilt["root"], rtol=1e-8, equal_nan=True)
    assert back.setup == t.setup and back.phases == t.phases and back.channels == t.channels
    meta = json.loads((out / "tiny.json").read_text())
    assert "doi:10.1016/j.ecoleng.2024.107259" in meta["citation"]
    with pytest.raises(OutputExistsError, match="--force"):
        import_pul([tiny], out)


def test_cli_import_pul(tiny, tmp_path, capsys):
    out = tmp_path / "data"
    assert main(["import-pul", str(tiny), "--out", str(out)]) == 0
    assert "tiny: 60 samples" in capsys.readouterr().out
    assert main(["import-pul", str(tiny), "--out", str(out)]) == 2  # exists, no --force
    assert "--force" in capsys.readouterr().err
    (out / "tiny.csv").write_text("mine")
    assert main(["import-pul", str(tiny), "--out", str(out), "--force"]) == 0
    kept = list(out.glob("tiny.csv.old-*"))
    assert len(kept) == 1 and kept[0].read_text() == "mine"  # moved aside, not deleted
    _break(tiny, 3, "force.raw", "??")
    assert main(["import-pul", str(tiny), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "data[3].force.raw" in err and "line" in err
    assert main(["import-pul", str(tiny), "--out", str(tiny.parent)]) == 2  # holds an input
    assert str(tiny.parent) in capsys.readouterr().err
    assert not (tmp_path / "x").exists()  # nothing written on error


def test_no_metadata_table_is_a_clear_error(tmp_path):
    pul = tmp_path / "a" / "b" / "tiny.pul"
    pul.parent.mkdir(parents=True)
    make_pul(pul)
    assert main(["import-pul", str(pul), "--out", str(tmp_path / "o")]) == 2


def test_dequantised_force_recovers_a_smooth_ramp_from_its_10_n_staircase():
    """A slow ramp (a 190 N peak, as gladstone_21's) read every 0.1 s and rounded to the load
    cell's 10 N, tared off the grid by 5 N: through the level crossings the force is within
    a small fraction of a quantum of the truth (the staircase is off by up to half of one)."""
    from treeinfer.data.pull_test import dequantised_force

    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.08, 0.27, 400))  # the recordings' irregular steps
    true = 190.0 * np.clip((t - t[20]) / (t[-20] - t[20]), 0, 1) + 3.0 * np.sin(t / 3.0)
    rec = np.round((true + 5.0) / 10.0) * 10.0 - 5.0  # rounded, then a tare of 5 N
    got = dequantised_force(t, rec)
    ramp = slice(40, 360)
    err_rec = np.sqrt(np.mean((rec[ramp] - true[ramp]) ** 2))
    err_got = np.sqrt(np.mean((got[ramp] - true[ramp]) ** 2))
    assert err_rec > 2.5  # about 10 / sqrt(12): the staircase's own error
    assert err_got < 0.4 * err_rec
    # a constant force (no level change) is left as it is
    flat = np.full(50, 120.0)
    np.testing.assert_array_equal(dequantised_force(np.arange(50.0), flat), flat)
    with pytest.raises(ValueError, match="differ"):
        dequantised_force(t[:5], rec[:6])


def test_dequantised_force_keeps_a_quick_multi_level_step_where_it_is():
    """A slow single-level ramp (0 -> 30 N over 30 s: each level lasts seconds) and then,
    after a plateau, a winch step of +50 N between two samples (as halloran_1's): the ramp is
    interpolated through its crossings, the step stays between its two samples (the force
    must not rise before it: interpolating to the step from the ramp's last crossing, 10 s
    earlier, would move 20 N of it seconds ahead of the tilts)."""
    from treeinfer.data.pull_test import dequantised_force

    t = np.arange(0.0, 60.0, 0.1)
    t_step = 45.05  # between the samples at 45.0 and 45.1
    true = np.clip(t - 5.0, 0.0, 30.0) + 50.0 * (t > t_step)
    rec = np.round((true + 5.0) / 10.0) * 10.0 - 5.0  # rounded, tared 5 N off the grid
    got = dequantised_force(t, rec)
    ramp = (t > 8.0) & (t < 33.0)
    assert np.sqrt(np.mean((got[ramp] - true[ramp]) ** 2)) < 1.5  # the staircase: ~2.9
    before = (t > 36.0) & (t < t_step)  # the plateau before the step
    np.testing.assert_allclose(got[before], true[before], atol=5.0 + 1e-9)
    assert np.max(np.abs(got[before] - rec[before])) <= 5.0 + 1e-9
    after = t > t_step
    np.testing.assert_allclose(got[after], rec[after], atol=5.0 + 1e-9)
    i = int(np.searchsorted(t, t_step))  # the step itself: the two readings either side
    assert got[i - 1] == rec[i - 1] and got[i] == rec[i]
    assert got[i] - got[i - 1] >= 40.0  # all of the step (50 N, read as 40-60 N)


def test_dequantised_force_stays_within_half_a_quantum_of_the_reading():
    """Whatever the record (random single and multi-level changes), the dequantised force is
    a value the reading allows: within half a quantum of it at every sample."""
    from treeinfer.data.pull_test import dequantised_force

    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.08, 0.27, 600))
    steps = rng.choice([0, 0, 0, 0, 1, -1, 2, 3, -4], size=600) * 10.0
    rec = np.cumsum(steps) - 5.0
    got = dequantised_force(t, rec)
    assert np.max(np.abs(got - rec)) <= 5.0 + 1e-9
    assert np.any(np.abs(got - rec) > 1.0)  # and it does move between the levels


def test_mangrove_history_thins_the_pre_load_to_one_sample_a_second():
    """``experiments/mangrove.py --history``: the samples before the fitted part that drive
    the model unfitted, from the record's first, one per second, none after ``start``."""
    from types import SimpleNamespace

    from experiments.mangrove import HISTORY_STEP_S, history

    rng = np.random.default_rng(2)
    t = np.cumsum(rng.uniform(0.08, 0.27, 900))
    test = SimpleNamespace(time=t)
    idx = history(test, 700, True)
    assert idx[0] == 0 and idx[-1] < 700
    assert np.all(np.diff(t[idx]) > 0.5 * HISTORY_STEP_S)
    assert idx.size == pytest.approx((t[699] - t[0]) / HISTORY_STEP_S, abs=2)
    assert history(test, 700, False).size == 0 and history(test, 0, True).size == 0
