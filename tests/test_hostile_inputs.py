"""Issue 28, section 4: no crash, no hang. Special files are refused unopened by every reader,
absurd sizes before any work, deep trees do not reach Python's recursion limit, and Ctrl-C ends
a command within seconds, leaving no staging folder."""

from __future__ import annotations

import os
import shutil
import signal
import site
import subprocess
import sys
import time
from pathlib import Path

import pytest

from treeinfer.cli.main import main
from treeinfer.errors import TreeinferError
from treeinfer.io.limits import check_tree_size, tree_depth
from treeinfer.io.safe_load import refuse_special_paths
from treeinfer.tree.model_paths import check_model_paths

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE_TREE = ROOT / "treeinfer" / "examples" / "two_branch.yaml"


@pytest.fixture
def ws(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("TREEINFER_JAX_CACHE", "off")
    monkeypatch.delenv("TREEINFER_ALLOW_LARGE", raising=False)
    monkeypatch.chdir(tmp_path)
    shutil.copy(EXAMPLE_TREE, tmp_path / "tree.yaml")
    return tmp_path


def _answers_2_fast(argv, capsys, *words, limit=60.0):  # generous: a shared, loaded box
    t0 = time.monotonic()
    rc = main([str(a) for a in argv])
    took = time.monotonic() - t0
    err = capsys.readouterr().err
    assert rc == 2, err
    assert took < limit, took
    for w in words:
        assert w in err, (w, err)
    return err


@pytest.mark.parametrize(
    "use",
    ["import-csv", "tree --from", "mjcf include", "urdf mesh", "pulls.yaml", "import-bag"],
)
def test_a_fifo_is_refused_without_blocking(ws, capsys, use):
    fifo = ws / "pipe"
    os.mkfifo(fifo)
    if use == "import-csv":
        argv = ["import-csv", fifo, "--out", ws / "imp"]
    elif use == "tree --from":
        argv = ["tree", "--from", fifo, "--out", ws / "t.yaml"]
    elif use == "mjcf include":
        (ws / "m.xml").write_text('<mujoco><include file="pipe"/></mujoco>')
        argv = ["tree", "--model", ws / "m.xml", "--out", ws / "t.yaml"]
    elif use == "urdf mesh":
        (ws / "m.urdf").write_text(
            '<robot name="r"><link name="b"><visual><geometry><mesh filename="pipe"/>'
            "</geometry></visual></link></robot>"
        )
        argv = ["tree", "--model", ws / "m.urdf", "--out", ws / "t.yaml"]
    elif use == "pulls.yaml":
        (ws / "d").mkdir()
        os.replace(fifo, ws / "d" / "pulls.yaml")
        (ws / "src.csv").write_text("time,force,displacement\n0,0,0\n0.1,1,0.01\n0.2,0,0\n")
        argv = ["import-csv", ws / "src.csv", "--out", ws / "d"]
    else:
        bag = ws / "b.bag"
        os.replace(fifo, bag)
        argv = ["import-bag", bag, "--out", ws / "imp"]
    _answers_2_fast(argv, capsys, "FIFO")
    assert not (ws / "imp").exists() and not (ws / "t.yaml").exists()


def test_a_symlink_loop_in_a_mesh_path_is_named(ws):
    os.symlink("b", ws / "a")
    os.symlink("a", ws / "b")
    (ws / "m.urdf").write_text(
        '<robot name="r"><link name="b"><visual><geometry><mesh filename="package://a"/>'
        "</geometry></visual></link></robot>"
    )
    with pytest.raises(TreeinferError, match="symbolic-link loop"):
        check_model_paths(ws / "m.urdf")


def test_include_chains_are_walked_without_recursion_and_loops_end(ws):
    for k in range(30):
        (ws / f"i{k}.xml").write_text(f'<mujoco><include file="i{k + 1}.xml"/></mujoco>')
    (ws / "i30.xml").write_text('<mujoco><include file="i0.xml"/></mujoco>')  # a loop
    with pytest.raises(TreeinferError, match="nested more than"):
        check_model_paths(ws / "i0.xml")


def test_refuse_special_paths_in_a_folder(ws):
    (ws / "bag").mkdir()
    (ws / "bag" / "ok.db3").write_bytes(b"x")
    refuse_special_paths(ws / "bag")
    os.symlink("/dev/zero", ws / "bag" / "z.db3")
    with pytest.raises(TreeinferError, match="character device"):
        refuse_special_paths(ws / "bag", "bag")


def _chain_yaml(n: int) -> str:
    rows = "".join(
        f"  - {{name: b{i}, parent: {'null' if i == 0 else f'b{i - 1}'}, length: 0.01, "
        "radius: 0.002}\n"
        for i in range(n)
    )
    return f"branches:\n{rows}grasp: {{branch: b{n - 1}}}\n"


def test_large_trees_are_refused_with_the_way_past_the_limit(ws, capsys):
    (ws / "chain.yaml").write_text(_chain_yaml(1000))
    _answers_2_fast(
        ["tree", "--from", ws / "chain.yaml", "--out", ws / "t.yaml"],
        capsys,
        "TREEINFER_ALLOW_LARGE",
    )
    _answers_2_fast(
        ["tree", "--kind", "fractal", "--depth", "25", "--out", ws / "f.yaml"], capsys, "67108863"
    )


def test_a_1000_branch_chain_passes_with_allow_large_and_no_recursion_error(
    ws, capsys, monkeypatch
):
    monkeypatch.setenv("TREEINFER_ALLOW_LARGE", "1")
    (ws / "chain.yaml").write_text(_chain_yaml(1000))
    rc = main(
        [
            "tree",
            "--from",
            str(ws / "chain.yaml"),
            "--out",
            str(ws / "t.yaml"),
            "--mjcf",
            str(ws / "t.xml"),
            "--urdf",
            str(ws / "t.urdf"),
        ]  # fmt: skip
    )
    assert rc == 0, capsys.readouterr().err
    assert (ws / "t.xml").read_text().count("<body") == 1000
    assert sys.getrecursionlimit() < 4000  # restored after the export


def test_tree_depth_and_size_limits():
    parents = {f"b{i}": (f"b{i - 1}" if i else None) for i in range(5000)}
    assert tree_depth(parents) == 5000  # iterative: no RecursionError
    assert tree_depth({"a": "b", "b": "a"}) > 10**9  # a cycle
    check_tree_size(10, 3)
    with pytest.raises(TreeinferError, match="more than the limit"):
        check_tree_size(10, 5000)


@pytest.mark.parametrize(
    "argv,flag",
    [
        (["calibrate", "--out", "c", "--datasets", "1000000000"], "--datasets"),
        (["warmup", "--steps", "1000000000"], "--steps"),
        (["warmup", "--", "--particles", "1000000000"], "infer --particles"),
        (["simulate", "--out", "c", "--duration", "1e12"], "--duration"),
        (["simulate", "--out", "c", "--n-traj", "1000000000"], "--n-traj"),
    ],
)
def test_absurd_sizes_are_refused_before_any_work(ws, capsys, argv, flag):
    argv = [argv[0], "--tree", str(ws / "tree.yaml"), *argv[1:]]
    _answers_2_fast(argv, capsys, flag, "--allow-large")
    assert not (ws / "c").exists()


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
@pytest.mark.parametrize("twice", [False, True])
def test_ctrl_c_ends_the_command_with_130_and_no_staging(tmp_path, twice):
    # HOME moves to tmp_path, which also moves Python's user site (pip install --user), and
    # PYTHONPATH is replaced: keep both where the test process finds its packages (on the test
    # machine MuJoCo was found only so, and the command died of ModuleNotFoundError, exit 3).
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    env = {
        **os.environ,
        "HOME": str(tmp_path),
        "PYTHONPATH": path,
        "PYTHONUSERBASE": os.environ.get("PYTHONUSERBASE", site.getuserbase()),
        "JAX_PLATFORMS": "cpu",
        "TREEINFER_JAX_CACHE": "off",
    }
    p = subprocess.Popen(
        [sys.executable, "-m", "treeinfer", "demo", "--quick", "--out", str(tmp_path / "d")],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    time.sleep(8)  # inside the simulation or the compiler
    p.send_signal(signal.SIGINT)
    if twice:
        time.sleep(0.2)
        p.send_signal(signal.SIGINT)
    t0 = time.monotonic()
    rc = p.wait(timeout=60)
    took = time.monotonic() - t0
    assert rc == 130, p.stderr.read().decode()[-2000:]
    assert took < 10, took
    left = [q for q in tmp_path.rglob("*") if q.name.endswith(".staging")]
    assert left == []


def test_a_csv_field_over_the_csv_modules_limit_is_a_user_error(ws, capsys):
    (ws / "huge.csv").write_text("time,force,displacement\n" + "1" * 200_000 + "\n")
    _answers_2_fast(["import-csv", ws / "huge.csv", "--out", ws / "imp"], capsys, "line 2")
