"""Tests for treeinfer.data.trajectories: CSV format, validation, velocity scheme, batching."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from treeinfer.data.trajectories import (
    Observations,
    Trajectory,
    add_noise,
    ground_truth_velocity,
    read_trajectory,
    read_trajectory_dir,
    stack_trajectories,
    validate_trajectory,
    velocity_from_displacement,
    write_trajectory,
)
from treeinfer.errors import ConfigError, TrajectoryFileError


def make_traj(n=40, dt=0.01, velocity=False, source="t.csv", seed=0):
    rng = np.random.default_rng(seed)
    t = 0.5 + dt * np.arange(n)
    f = 3.0 * np.sin(np.linspace(0, 2, n)) + 0.01 * rng.standard_normal(n)
    x = 0.05 * (1 - np.cos(np.linspace(0, 2, n))) + 1e-4 * rng.standard_normal(n)
    v = np.gradient(x, dt, edge_order=2) if velocity else None
    return Trajectory(t, f, x, v, source)


def csv_text(n=5, dt=0.01, cols=("time", "force", "displacement"), comments=("meta",)):
    lines = [f"# {c}" for c in comments] + [",".join(cols)]
    for i in range(n):
        vals = {"time": i * dt, "force": 1.0 + i, "displacement": 0.001 * i, "velocity": 0.1}
        lines.append(",".join(repr(vals.get(c, 0.0)) for c in cols))
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- round trip


@pytest.mark.parametrize("velocity", [False, True])
def test_round_trip_is_exact(tmp_path, velocity):
    traj = make_traj(velocity=velocity)
    path = write_trajectory(tmp_path / "a.csv", traj)
    back = read_trajectory(path)
    for name in ("time", "force", "displacement"):
        np.testing.assert_array_equal(getattr(back, name), getattr(traj, name))
    if velocity:
        np.testing.assert_array_equal(back.velocity, traj.velocity)
    else:
        assert back.velocity is None
    assert back.source == "a.csv"
    assert back.n_steps == 40
    assert back.dt == pytest.approx(0.01, rel=1e-12)
    text = path.read_text()
    header = "time,force,displacement" + (",velocity" if velocity else "")
    assert text.startswith(header + "\n")  # header first: pandas/spreadsheets read it as is
    assert not list(tmp_path.glob(".*tmp"))  # atomic write left no temp file


def test_written_csv_parses_with_csv_module_and_comments_still_read(tmp_path):
    import csv

    traj = make_traj()
    with pytest.warns(DeprecationWarning, match="ignored"):
        path = write_trajectory(tmp_path / "a.csv", traj, comments=["robot: ur5"])
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))  # what pandas.read_csv(path) sees: header on line 1
    assert list(rows[0]) == ["time", "force", "displacement"] and len(rows) == traj.n_steps
    np.testing.assert_array_equal([float(r["force"]) for r in rows], traj.force)
    # reading still accepts '#' comments before the header, between rows and at the end
    lines = path.read_text().splitlines()
    mixed = ["# before", lines[0], lines[1], "# between", *lines[2:], "# after"]
    (tmp_path / "m.csv").write_text("\n".join(mixed) + "\n")
    back = read_trajectory(tmp_path / "m.csv")
    np.testing.assert_array_equal(back.force, traj.force)


def test_reader_accepts_any_column_order_case_crlf_and_blank_lines(tmp_path):
    p = tmp_path / "b.csv"
    p.write_bytes(
        b"\xef\xbb\xbf# c\r\n Displacement , TIME,force\r\n0,0,1\r\n\r\n0.1,0.1,2\r\n0.2,0.2,3\r\n"
    )
    tr = read_trajectory(p)
    np.testing.assert_array_equal(tr.time, [0, 0.1, 0.2])
    np.testing.assert_array_equal(tr.force, [1, 2, 3])
    np.testing.assert_array_equal(tr.displacement, [0, 0.1, 0.2])


def test_write_refuses_invalid_trajectory(tmp_path):
    bad = make_traj()._replace(displacement=np.full(40, 12.0))
    with pytest.raises(TrajectoryFileError, match="millimetres"):
        write_trajectory(tmp_path / "bad.csv", bad)
    assert not list(tmp_path.iterdir())


# ----------------------------------------------------------------------------- bad inputs


def _replace_line(text, lineno, new):
    lines = text.split("\n")
    lines[lineno - 1] = new
    return "\n".join(lines)


# csv_text(): line 1 comment, line 2 header, data rows on lines 3.. (row i on line 3 + i)
BAD_CASES = {
    "missing column": (csv_text(cols=("time", "force")), 2, "missing column(s) ['displacement']"),
    "unknown column": (
        csv_text(cols=("time", "force", "displacement", "torque")),
        2,
        "unknown column(s) ['torque']",
    ),
    "duplicate column": (
        csv_text().replace("time,force,displacement", "time,force,force"),
        2,
        "duplicate column",
    ),
    "empty column name": (
        csv_text().replace("time,force,displacement", "time,force,displacement,"),
        2,
        "empty column",
    ),
    "no header": (_replace_line(csv_text(), 2, "0,1,0"), 2, "missing header"),
    "non-numeric": (
        _replace_line(csv_text(), 5, "0.02,abc,0.002"),
        5,
        "column 'force': non-numeric value 'abc'",
    ),
    "empty cell": (_replace_line(csv_text(), 4, "0.01,,0.001"), 4, "column 'force': empty cell"),
    "too few cells": (
        _replace_line(csv_text(), 6, "0.03,4.0"),
        6,
        "row has 2 cell(s) but the header has 3",
    ),
    "too many cells": (_replace_line(csv_text(), 3, "0.0,1.0,0.0,7"), 3, "row has 4 cell(s)"),
    "nan": (_replace_line(csv_text(), 4, "0.01,nan,0.001"), 4, "column 'force' is 'nan'"),
    "inf": (_replace_line(csv_text(), 7, "0.04,5.0,inf"), 7, "column 'displacement' is 'inf'"),
    "overflow to inf": (_replace_line(csv_text(), 7, "0.04,1e999,0.004"), 7, "NaN/inf"),
    "not increasing": (
        _replace_line(csv_text(), 5, "0.01,3.0,0.002"),
        5,
        "not after the previous time",
    ),
    "uneven step": (_replace_line(csv_text(n=8), 6, "0.0305,4.0,0.003"), 6, "uneven time step"),
    "displacement in mm": (
        _replace_line(csv_text(), 6, "0.03,4.0,30.0"),
        6,
        "looks like millimetres, expected metres",
    ),
    "time in ms": (csv_text(dt=10.0), 4, "looks like milliseconds, expected seconds"),
    "time step of 2 s": (csv_text(n=50, dt=2.0), 4, "looks like milliseconds"),
    "force too large": (_replace_line(csv_text(), 4, "0.01,25000,0.001"), 4, "implausible"),
    "velocity in mm/s": (
        csv_text(cols=("time", "force", "displacement", "velocity")).replace(
            ",0.1\n", ",100.0\n", 1
        ),
        3,
        "millimetres per second",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_input_names_file_line_and_problem(tmp_path, case):
    text, line, problem = BAD_CASES[case]
    p = tmp_path / "pull.csv"
    p.write_text(text)
    with pytest.raises(TrajectoryFileError) as exc:
        read_trajectory(p)
    msg = str(exc.value)
    assert str(p) in msg
    assert f"line {line}:" in msg, msg
    assert problem in msg, msg


@pytest.mark.parametrize(
    "text, problem",
    [
        ("", "file is empty"),
        ("# only a comment\n\n", "file is empty"),
        ("time,force,displacement\n", "header only"),
        ("time,force,displacement\n0,0,0\n0.01,0,0\n", "only 2 data row(s)"),
    ],
)
def test_empty_and_short_files(tmp_path, text, problem):
    p = tmp_path / "e.csv"
    p.write_text(text)
    with pytest.raises(TrajectoryFileError, match=r"e\.csv") as exc:
        read_trajectory(p)
    assert problem in str(exc.value)


def test_unreadable_and_binary_files(tmp_path):
    with pytest.raises(TrajectoryFileError, match="cannot read"):
        read_trajectory(tmp_path / "missing.csv")
    p = tmp_path / "bin.csv"
    p.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(TrajectoryFileError, match="not UTF-8"):
        read_trajectory(p)


def test_validate_trajectory_checks_shapes():
    tr = make_traj()
    with pytest.raises(TrajectoryFileError, match="'force' has 39 values"):
        validate_trajectory(tr._replace(force=tr.force[:-1]))
    ok = validate_trajectory(tr._replace(force=list(tr.force)))
    assert ok.force.dtype == np.float64


# ----------------------------------------------------------------------------- folders


def test_read_dir_sorted_and_dt_mismatch(tmp_path):
    for name, seed in [("b.csv", 1), ("a.csv", 2), ("c.csv", 3)]:
        write_trajectory(tmp_path / name, make_traj(seed=seed))
    (tmp_path / "notes.txt").write_text("ignored")
    trajs = read_trajectory_dir(tmp_path)
    assert [t.source for t in trajs] == ["a.csv", "b.csv", "c.csv"]
    np.testing.assert_array_equal(trajs[0].force, make_traj(seed=2).force)

    write_trajectory(tmp_path / "d.csv", make_traj(dt=0.02))
    write_trajectory(tmp_path / "e.csv", make_traj(dt=0.0100001))
    with pytest.raises(TrajectoryFileError) as exc:
        read_trajectory_dir(tmp_path)
    msg = str(exc.value)
    assert "d.csv (dt=0.02 s)" in msg and "e.csv" in msg
    assert "a.csv" in msg and "b.csv (" not in msg


def test_read_dir_errors(tmp_path):
    with pytest.raises(TrajectoryFileError, match="does not exist"):
        read_trajectory_dir(tmp_path / "nope")
    (tmp_path / "x.txt").write_text("")
    with pytest.raises(TrajectoryFileError, match=r"no trajectory files matching '\*\.csv'"):
        read_trajectory_dir(tmp_path)
    (tmp_path / "bad.csv").write_text("time,force\n")
    with pytest.raises(TrajectoryFileError, match=r"bad\.csv, line 1: missing column"):
        read_trajectory_dir(tmp_path)


# ----------------------------------------------------------------------------- velocity


def test_velocity_matches_numpy_gradient_numpy_and_jax():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((3, 4, 17))
    dt = 0.013
    ref = np.gradient(x, dt, axis=-1, edge_order=2)
    v_np = velocity_from_displacement(x, dt)
    assert isinstance(v_np, np.ndarray) and v_np.dtype == np.float64
    np.testing.assert_allclose(v_np, ref, rtol=1e-12, atol=1e-12)

    xj = jnp.asarray(x, dtype=jnp.float32)
    v_jit = jax.jit(velocity_from_displacement)(xj, dt)
    v_vmap = jax.vmap(velocity_from_displacement, in_axes=(0, None))(xj, dt)
    assert v_jit.shape == x.shape
    np.testing.assert_allclose(v_jit, ref, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(v_vmap, ref, rtol=1e-4, atol=1e-4)
    # a traced dt also works (the simulator may carry dt as data)
    v_dt = jax.jit(lambda d: velocity_from_displacement(xj[0, 0], d))(jnp.float32(dt))
    np.testing.assert_allclose(v_dt, ref[0, 0], rtol=1e-4, atol=1e-4)


def test_velocity_second_order_against_analytic_derivative():
    def max_err(n):
        t = np.linspace(0.0, 2.0, n)
        dt = t[1] - t[0]
        v = velocity_from_displacement(np.sin(3 * t), dt)
        err = np.abs(v - 3 * np.cos(3 * t))
        return err.max(), max(err[0], err[-1])

    (e1, edge1), (e2, edge2) = max_err(101), max_err(201)
    assert e1 < 5e-3
    # halving the step divides the error by ~4, at the ends too
    assert 3.5 < e1 / e2 < 4.5
    assert 3.5 < edge1 / edge2 < 4.5
    # exact for quadratics (second order everywhere)
    t = np.arange(6) * 0.1
    np.testing.assert_allclose(velocity_from_displacement(t**2 - t, 0.1), 2 * t - 1, atol=1e-12)


def test_velocity_needs_three_samples():
    with pytest.raises(ValueError, match="at least 3"):
        velocity_from_displacement(np.zeros(2), 0.1)


def test_ground_truth_velocity_prefers_recorded():
    tr = make_traj()
    np.testing.assert_allclose(
        ground_truth_velocity(tr), np.gradient(tr.displacement, 0.01, edge_order=2), rtol=1e-9
    )
    rec = np.arange(40.0)
    np.testing.assert_array_equal(ground_truth_velocity(tr._replace(velocity=rec)), rec)


# ----------------------------------------------------------------------------- batching, noise


def test_stack_pads_with_last_value_and_masks():
    a, b = make_traj(n=10, seed=1, source="a"), make_traj(n=6, seed=2, source="b")
    obs = stack_trajectories([a, b])
    assert isinstance(obs, Observations)
    assert (
        obs.force.shape == obs.displacement.shape == obs.velocity.shape == obs.mask.shape == (2, 10)
    )
    assert obs.dt == pytest.approx(0.01)
    np.testing.assert_array_equal(obs.mask[1], [True] * 6 + [False] * 4)
    assert obs.mask[0].all()
    np.testing.assert_array_equal(obs.force[1, :6], b.force)
    np.testing.assert_array_equal(obs.force[1, 6:], b.force[-1])
    np.testing.assert_array_equal(obs.displacement[1, 6:], b.displacement[-1])
    np.testing.assert_allclose(obs.velocity[1, :6], np.gradient(b.displacement, 0.01, edge_order=2))
    np.testing.assert_array_equal(obs.velocity[1, 6:], 0.0)

    with pytest.raises(TrajectoryFileError, match=r"c \(dt=0\.02"):
        stack_trajectories([a, make_traj(dt=0.02, source="c")])
    with pytest.raises(TrajectoryFileError, match="no trajectories"):
        stack_trajectories([])


def test_add_noise_seeded_and_calibrated():
    tr = make_traj(n=20000, velocity=True)
    n1 = add_noise(tr, 0.5, 0.002, np.random.default_rng(3))
    n2 = add_noise(tr, 0.5, 0.002, 3)
    np.testing.assert_array_equal(n1.force, n2.force)
    assert n1.velocity is None
    np.testing.assert_array_equal(n1.time, tr.time)
    rf, rx = n1.force - tr.force, n1.displacement - tr.displacement
    assert np.std(rf) == pytest.approx(0.5, rel=0.03) and abs(np.mean(rf)) < 0.02
    assert np.std(rx) == pytest.approx(0.002, rel=0.03)
    assert abs(np.corrcoef(rf, rx)[0, 1]) < 0.05
    np.testing.assert_array_equal(add_noise(tr, 0.0, 0.0, 1).force, tr.force)
    with pytest.raises(ConfigError):
        add_noise(tr, -1.0, 0.0, 0)


# ----------------------------------------------------------------------------- fuzzing


def _load_or_user_error(tmp_path, data: bytes):
    p = tmp_path / "fuzz.csv"
    p.write_bytes(data)
    try:
        tr = read_trajectory(p)
    except TrajectoryFileError as e:
        assert "fuzz.csv" in str(e)
        return None
    # a successful load must be a valid trajectory
    assert tr.n_steps >= 3 and np.all(np.diff(tr.time) > 0)
    assert np.all(np.isfinite(tr.force)) and np.all(np.isfinite(tr.displacement))
    return tr


FUZZ = settings(
    max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


@FUZZ
@given(data=st.binary(max_size=300))
def test_fuzz_random_bytes(tmp_path, data):
    _load_or_user_error(tmp_path, data)


@FUZZ
@given(
    text=st.text(
        alphabet=st.sampled_from(
            list("0123456789.,-+eE#\n\r\t naniftimeforcedisplacementvelocity")
        ),
        max_size=300,
    )
)
def test_fuzz_random_text(tmp_path, text):
    _load_or_user_error(tmp_path, text.encode())


_GARBAGE = st.sampled_from(
    ["nan", "inf", "-inf", "", "abc", "1e999", "1,2", "#x", "\x00", "é", "1e-320", "-0"]
)


@st.composite
def mutated_csv(draw):
    n = draw(st.integers(3, 12))
    velocity = draw(st.booleans())
    cols = ["time", "force", "displacement"] + (["velocity"] if velocity else [])
    lines = ["# meta", ",".join(cols)]
    for i in range(n):
        lines.append(",".join(repr(v) for v in [i * 0.01, 1.0 + i, 0.001 * i, 0.1][: len(cols)]))
    for _ in range(draw(st.integers(0, 4))):
        op = draw(st.sampled_from(["drop_cell", "set_cell", "swap", "dup", "delete", "insert"]))
        i = draw(st.integers(0, len(lines) - 1))
        j = draw(st.integers(0, len(lines) - 1))
        cells = lines[i].split(",")
        if op == "drop_cell" and len(cells) > 1:
            del cells[draw(st.integers(0, len(cells) - 1))]
            lines[i] = ",".join(cells)
        elif op == "set_cell":
            cells[draw(st.integers(0, len(cells) - 1))] = draw(_GARBAGE)
            lines[i] = ",".join(cells)
        elif op == "swap":
            lines[i], lines[j] = lines[j], lines[i]
        elif op == "dup":
            lines.insert(j, lines[i])
        elif op == "delete" and len(lines) > 1:
            del lines[i]
        elif op == "insert":
            lines.insert(i, draw(st.text(max_size=20)))
    return "\n".join(lines) + "\n"


@FUZZ
@given(text=mutated_csv())
def test_fuzz_mutated_csv(tmp_path, text):
    _load_or_user_error(tmp_path, text.encode("utf-8", "surrogatepass"))


def test_unmutated_fuzz_seed_loads(tmp_path):
    # the fuzz generator's starting point is valid, so the fuzz tests also exercise loads
    tr = _load_or_user_error(tmp_path, csv_text(n=6).encode())
    assert tr is not None and tr.n_steps == 6


def test_band_csv_reads_with_csv_module(tmp_path):
    import csv

    from treeinfer.data.trajectories import write_band_csv

    t = np.arange(4) * 0.1
    path = write_band_csv(tmp_path / "p.csv", t, 2 * t, None, t, t - 1, t + 1, t - 2, t + 2)
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == [
        "time",
        "force",
        "recorded",
        "mean",
        "lower",
        "upper",
        "predictive_lower",
        "predictive_upper",
    ]
    assert rows[2]["recorded"] == "" and float(rows[2]["upper"]) == pytest.approx(1.2)
    with pytest.raises(ConfigError, match="column 'mean' has 3 values"):
        write_band_csv(tmp_path / "q.csv", t, t, t, t[:3], t, t)
