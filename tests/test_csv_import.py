"""Tests for treeinfer.data.import_csv (import-csv): units, time base, tare, trim, errors,
sidecar."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from treeinfer.data.import_csv import (
    DISPLACEMENT_UNITS,
    FORCE_UNITS,
    TIME_UNITS,
    convert_file,
    import_csv,
    parse_units,
)
from treeinfer.data.pulls import read_pulls
from treeinfer.data.trajectories import read_trajectory
from treeinfer.errors import ConfigError, TrajectoryFileError


def r(v) -> str:
    """Shortest round-trip text of a float (numpy scalars included)."""
    return repr(float(v))


def write_log(path, header, rows, comments=()):
    lines = [f"# {c}" for c in comments]
    if header:
        lines.append(",".join(header))
    lines += [",".join(str(v) for v in r) for r in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def ramp(n=40, dt=0.5, idle=5, f_rest=0.0, k=2.0):
    """A push: ``idle`` rest samples, a ramp up, a hold and ``idle`` rest samples (N, m)."""
    f = np.concatenate([np.zeros(idle), np.linspace(0, 3, n), np.full(5, 3.0), np.zeros(idle)])
    x = f / k / 100  # linear spring, m
    x[-idle:] = 0.0
    t = dt * np.arange(f.size)
    return t, f + f_rest, x


# ----------------------------------------------------------------------------- units


def test_unit_table_against_definitions():
    # independent figures: NIST SP 811 (gf = 9.80665e-3 N, lbf = 4.448222 N, in = 25.4 mm)
    assert FORCE_UNITS["gf"] == pytest.approx(9.80665e-3, rel=1e-12)
    assert FORCE_UNITS["kgf"] == pytest.approx(9.80665, rel=1e-12)
    assert FORCE_UNITS["lbf"] == pytest.approx(4.4482216152605, rel=1e-12)
    assert FORCE_UNITS["mN"] == 1e-3 and FORCE_UNITS["kN"] == 1e3
    assert DISPLACEMENT_UNITS == {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254}
    assert TIME_UNITS == {"s": 1.0, "ms": 0.001}
    assert parse_units("time=ms, force=GF,displacement=mm") == {
        "time": "ms",
        "force": "gf",
        "displacement": "mm",
    }
    for bad in ("force=stone", "mass=kg", "time"):
        with pytest.raises(ConfigError):
            parse_units(bad)


@pytest.mark.parametrize(
    "funit, dunit, tunit",
    [
        ("gf", "mm", "ms"),
        ("lbf", "in", "s"),
        ("kgf", "cm", "ms"),
        ("mN", "m", "s"),
        ("kN", "mm", "s"),
        ("N", "m", "s"),
    ],
)
def test_units_convert(tmp_path, funit, dunit, tunit):
    t, f, x = ramp()
    rows = zip(t / TIME_UNITS[tunit], f / FORCE_UNITS[funit], x / DISPLACEMENT_UNITS[dunit])
    src = write_log(
        tmp_path / "log.csv", ["Time", "Load", "Pos"], [[r(v) for v in row] for row in rows]
    )
    traj, steps = convert_file(
        src,
        time="Time",
        force="load",
        displacement=2,
        units={"time": tunit, "force": funit, "displacement": dunit},
    )
    np.testing.assert_allclose(traj.force, f, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(traj.displacement, x, rtol=1e-12, atol=1e-15)
    assert traj.dt == pytest.approx(0.5)
    if funit != "N":
        assert any(s.startswith(f"force: {funit} -> N") for s in steps)


# ----------------------------------------------------------------------------- time base


def test_wraparound_unwrapped_and_reported(tmp_path):
    t, f, x = ramp()
    t_ms = (1000 * t + 64000) % 65536  # a 16-bit millisecond counter that wraps mid-push
    assert np.any(np.diff(t_ms) < 0)
    rows = [[r(a), r(b), r(c)] for a, b, c in zip(t_ms, f, x)]
    src = write_log(tmp_path / "log.csv", ["t", "f", "x"], rows)
    traj, steps = convert_file(src, time="t", force="f", displacement="x", units="time=ms")
    np.testing.assert_allclose(traj.time, t - t[0], atol=1e-9)
    wrap = [s for s in steps if "wraps around" in s]
    assert wrap and "log.csv, line" in wrap[0] and "unwrapped 1" in wrap[0]
    # with --dt the time column is replaced and the wrap still reported
    traj2, steps2 = convert_file(
        src, time="t", force="f", displacement="x", units="time=ms", dt=0.5
    )
    np.testing.assert_allclose(traj2.time, t - t[0], atol=1e-12)
    assert any("wraps around" in s for s in steps2)
    assert any("uniform time base" in s for s in steps2)


def test_jitter_resampled_and_missing_time(tmp_path):
    t, f, x = ramp()
    rng = np.random.default_rng(0)
    tj = t + rng.uniform(-0.02, 0.02, t.size)
    src = write_log(
        tmp_path / "j.csv", ["t", "f", "x"], [[r(a), r(b), r(c)] for a, b, c in zip(tj, f, x)]
    )
    traj, steps = convert_file(src, time="t", force="f", displacement="x")
    assert any("jitter" in s for s in steps)
    np.testing.assert_allclose(np.diff(traj.time), np.diff(traj.time)[0], rtol=1e-9)
    # a linear ramp resamples exactly on its linear part
    src2 = write_log(tmp_path / "n.csv", ["f", "x"], [[r(b), r(c)] for b, c in zip(f, x)])
    with pytest.raises(ConfigError, match="no time column"):
        convert_file(src2, time=None, force="f", displacement="x")
    traj2, steps2 = convert_file(src2, time=None, force=0, displacement=1, dt=0.5)
    assert traj2.dt == pytest.approx(0.5) and "no time column" in steps2[1]


# ----------------------------------------------------------------------------- tare / trim / zero


def test_tare_trim_zero(tmp_path):
    t, f, x = ramp(idle=8, f_rest=0.8)
    x = x + 0.002  # stepper position not zero at the start
    rng = np.random.default_rng(1)
    f_noisy = f + 0.01 * rng.standard_normal(f.size)
    src = write_log(
        tmp_path / "p.csv",
        ["time", "force", "displacement"],
        [[r(a), r(b), r(c)] for a, b, c in zip(t, f_noisy, x)],
    )
    raw, _ = convert_file(src)
    assert raw.force[0] == pytest.approx(0.8, abs=0.05)
    traj, steps = convert_file(src, tare=True, trim=True, zero_displacement="first")
    tare = [s for s in steps if s.startswith("tare")]
    assert tare and "0.8" in tare[0]
    assert abs(traj.force[0]) < 0.05 and abs(traj.force[-1]) < 0.05  # rest force removed
    assert traj.displacement[0] == 0.0
    # trimmed: the idle start and end are gone, one rest sample is kept on each side
    # (activity threshold: 5% of the 3 N peak; the ramp rises 0.077 N per sample)
    onset = int(np.flatnonzero(traj.force > 0.15)[0])
    assert onset in range(1, 5), onset
    assert traj.n_steps - 5 <= np.flatnonzero(traj.force > 0.15)[-1] <= traj.n_steps - 2
    trim = [s for s in steps if s.startswith("trim: dropped")]
    assert trim and traj.n_steps < f.size - 10
    np.testing.assert_allclose(traj.force.max(), 3.0, atol=0.05)


def _pull(idle_before: int, hold: int, release: bool, idle_after: int = 12):
    """A pull: rest, a ramp to 3 N, a loaded hold of ``hold`` samples, then (``release``) the
    force back to rest and ``idle_after`` rest samples; a spring of 0.5 cm/N (N, m, s)."""
    rng = np.random.default_rng(3)
    parts = [np.zeros(idle_before), np.linspace(0, 3, 30), np.full(hold, 3.0)]
    if release:
        parts += [np.linspace(3, 0, 10), np.zeros(idle_after)]
    f = np.concatenate(parts)
    x = f / 200.0
    t = 0.01 * np.arange(f.size)
    return t, f + 0.005 * rng.standard_normal(f.size), x


@pytest.mark.parametrize("release", [False, True])
def test_trim_keeps_a_loaded_hold(tmp_path, release):
    """Issue 29: --trim removes the idle lead-in and the tail after a release, never a loaded
    hold at the end (a plateau of force, the samples that identify the stiffness best)."""
    t, f, x = _pull(idle_before=20, hold=129, release=release)
    src = write_log(
        tmp_path / "pull.csv",
        ["time", "force", "displacement"],
        [[r(a), r(b), r(c)] for a, b, c in zip(t, f, x)],
    )
    record = {}
    traj, steps = convert_file(src, trim=True, record=record)
    hold_end = 20 + 30 + 129  # samples up to the end of the hold
    line = next(s for s in steps if s.startswith("trim:"))
    assert "dropped 19 idle sample(s) of lead-in" in line  # one rest sample kept
    assert record["lead_in_samples"] == 19
    if release:
        # the hold, the release ramp and one rest sample after it are kept; the rest goes
        assert traj.n_steps == f.size - 19 - record["tail_samples"]
        assert 8 <= record["tail_samples"] <= 11 and record["ends_with"] == "release"
        assert "after the release" in line
        assert np.all(np.abs(traj.force[-1]) < 0.05)
    else:
        assert traj.n_steps == f.size - 19  # everything from the ramp's foot to the end
        assert record == {**record, "tail_samples": 0, "ends_with": "loaded hold"}
        assert "loaded hold" in line
        np.testing.assert_allclose(traj.force[-129:], f[-129:], atol=1e-9)  # the whole hold
    assert traj.n_steps >= hold_end - 19 + (0 if not release else 10)
    assert record["kept_from_s"] == pytest.approx(0.19)
    # the record reaches pulls.yaml beside the grasp point
    out = tmp_path / "data"
    res = import_csv([src], out, trim=True, grasp_fraction=0.8)
    entry = read_pulls(res.sidecar).pulls["pull.csv"]
    assert entry.fraction == 0.8 and entry.trimmed["lead_in_samples"] == 19
    assert entry.trimmed["ends_with"] == ("release" if release else "loaded hold")
    assert "ends_with" in (out / "pulls.yaml").read_text()


def test_zero_at_contact(tmp_path):
    t, f, x = ramp(idle=6)
    x = x + np.concatenate([np.linspace(-0.01, 0, 6), np.zeros(x.size - 6)])  # approach
    src = write_log(
        tmp_path / "c.csv",
        ["time", "force", "displacement"],
        [[r(a), r(b), r(c)] for a, b, c in zip(t, f, x)],
    )
    traj, steps = convert_file(src, zero_displacement="contact")
    assert any("approach sample" in s for s in steps)
    assert any("after the force returns to rest" in s for s in steps)
    assert traj.displacement[0] == pytest.approx(0.0, abs=1e-12) and traj.force[0] == 0.0
    # 6 approach samples dropped (the ramp starts at rest), and the 5 after the release
    assert traj.n_steps == f.size - 6 - 5
    # contact position from the loaded samples: the spring line through the origin
    np.testing.assert_allclose(traj.displacement, traj.force / 200.0, atol=1e-12)


def test_sign_check_warns(tmp_path):
    t, f, x = ramp()
    src = write_log(
        tmp_path / "s.csv",
        ["time", "force", "displacement"],
        [[r(a), r(b), r(-c)] for a, b, c in zip(t, f, x)],
    )
    with pytest.warns(UserWarning, match="opposite directions"):
        _, steps = convert_file(src)
    assert any(s.startswith("WARNING") for s in steps)


# ----------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    "text, kwargs, message",
    [
        (
            "time,force,disp\n0,1,2\n",
            {"displacement": "x"},
            "line 1: no displacement column named 'x'",
        ),
        ("time,force,x\n0,1,2\n", {"displacement": 5}, "column index 5 is out of range"),
        (
            "time,force,x\n0,1,2\n0.5,abc,3\n1,2,3\n",
            {"displacement": "x"},
            "line 3, column 'force' (force): non-numeric value 'abc'",
        ),
        (
            "# c\ntime,force,x\n0,1,2\n0.5,,3\n1,2,3\n",
            {"displacement": "x"},
            "line 4, column 'force'",
        ),
        ("time,force,x\n0,1,2\n0.5,1\n", {"displacement": "x"}, "line 3: row has 2 cell(s)"),
        ("time,force,x\n0,1,2\n0.5,1,2\n", {"displacement": "x"}, "only 2 data row(s)"),
        (
            "time,force,x\n0,1,2\n0.5,1,2\n0.4,1,2\n0.9,1,2\n",
            {"displacement": "x"},
            "goes backwards at",
        ),
    ],
)
def test_errors_name_file_and_line(tmp_path, text, kwargs, message):
    src = tmp_path / "bad.csv"
    src.write_text(text)
    with pytest.raises(TrajectoryFileError) as e:
        convert_file(src, **kwargs)
    assert "bad.csv" in str(e.value) and message in str(e.value)


# ----------------------------------------------------------------------------- whole import


def test_import_writes_folder_sidecar_and_provenance(tmp_path, capsys):
    t, f, x = ramp()
    srcs = []
    for name, scale in (("low", 1.0), ("mid", 2.0)):
        rows = [[r(a), r(b / FORCE_UNITS["gf"]), r(scale * c * 1000)] for a, b, c in zip(t, f, x)]
        srcs.append(
            write_log(tmp_path / f"{name}.txt", ["t", "gf", "mm"], rows, comments=["logger v1"])
        )
    out = tmp_path / "data"
    res = import_csv(
        [srcs[0]],
        out,
        time="t",
        force="gf",
        displacement="mm",
        units="force=gf,displacement=mm",
        grasp_branch="stem",
        grasp_distance=0.1,
        direction="horizontal",
    )
    res2 = import_csv(
        [srcs[1]],
        out,
        time="t",
        force="gf",
        displacement="mm",
        units="force=gf,displacement=mm",
        grasp_branch="stem",
        grasp_fraction=0.5,
        direction="1,0,0",
    )
    assert [p.name for p in res.paths + res2.paths] == ["low.csv", "mid.csv"]
    side = read_pulls(out / "pulls.yaml")
    assert side.pulls["low.csv"].distance == 0.1 and side.pulls["low.csv"].direction == "horizontal"
    assert side.pulls["mid.csv"].fraction == 0.5
    assert side.pulls["mid.csv"].direction == (1.0, 0.0, 0.0)
    back = read_trajectory(out / "mid.csv")
    np.testing.assert_allclose(back.displacement, 2 * x, atol=1e-15)
    prov = json.loads((out / "import.json").read_text())
    assert set(prov["files"]) == {"low.csv", "mid.csv"}
    assert "force: gf -> N" in res.report()
    # the written CSV starts with its header and parses with the csv module
    with open(out / "low.csv", newline="") as fh:
        first = fh.readline()
        assert first.strip() == "time,force,displacement"
        fh.seek(0)
        rows = list(csv.DictReader(fh))
    assert len(rows) == t.size and float(rows[3]["force"]) == pytest.approx(f[3])
    with pytest.raises(ConfigError, match="already holds"):
        import_csv([srcs[0]], out, time="t", force="gf", displacement="mm")
    with pytest.raises(ConfigError, match="not both"):
        import_csv([srcs[0]], tmp_path / "o2", grasp_fraction=0.5, grasp_distance=0.1)
    with pytest.raises(ConfigError, match="zero vector"):
        import_csv([srcs[0]], tmp_path / "o3", direction="0,0,0")
    assert not (tmp_path / "o3").exists()


# ----------------------------------------------------------------------------- command line


def test_cli_import_csv(tmp_path, capsys):
    from treeinfer.cli.main import main

    t, f, x = ramp(f_rest=0.5)
    rows = [[r(1000 * a), r(b / FORCE_UNITS["gf"]), r(1000 * c)] for a, b, c in zip(t, f, x)]
    src = write_log(tmp_path / "log.csv", ["ms", "g", "mm"], rows)
    out = tmp_path / "d"
    argv = [
        "import-csv",
        str(src),
        "--out",
        str(out),
        "--time-column",
        "ms",
        "--force-column",
        "g",
        "--displacement-column",
        "mm",
        "--units",
        "time=ms,force=gf,displacement=mm",
        "--tare",
        "--trim",
        "--grasp-fraction",
        "0.5",
        "--direction",
        "horizontal",
    ]
    assert main(argv) == 0
    stdout = capsys.readouterr().out
    assert "force: gf -> N" in stdout and "tare: subtracted" in stdout and "trim:" in stdout
    assert read_pulls(out / "pulls.yaml").pulls["log.csv"].fraction == 0.5
    assert read_trajectory(out / "log.csv").force.max() == pytest.approx(3.0, abs=1e-6)
    assert main(argv) == 2  # same name again: refused ...
    assert "already holds" in capsys.readouterr().err
    assert main(argv + ["--force"]) == 0  # ... unless --force (overwrite, as everywhere)
    capsys.readouterr()
    bad = ["import-csv", str(src), "--out", str(tmp_path / "e"), "--time-column", "ms"]
    bad += ["--force-column", "g", "--displacement-column", "nope"]
    assert main(bad) == 2
    err = capsys.readouterr().err
    assert "log.csv, line 1: no displacement column named 'nope'" in err
    assert "Traceback" not in err
