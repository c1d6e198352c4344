"""Issue 28, section 1: nothing treeinfer did not write is ever deleted, and no command writes
over its own inputs.

Every command is run through the real command line (:func:`treeinfer.cli.main.main`) on tiny
inputs; each refusal must come before any work: exit 2, a message naming both paths, the inputs
byte-for-byte unchanged, and no staging folder, ``.old-`` copy or output left behind.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import pytest

from treeinfer.cli.main import main
from treeinfer.errors import OutputExistsError
from treeinfer.io import atomic as _io
from treeinfer.io.atomic import OUTPUT_MARKER, check_output_dir, staged_output_dir
from treeinfer.io.ownership import move_aside, refuse_overlap

EXAMPLE_TREE = Path(__file__).resolve().parents[1] / "treeinfer" / "examples" / "two_branch.yaml"


def _snapshot(root: Path) -> dict[str, str]:
    """Every entry under ``root`` (files by sha256, links by target, folders by name)."""
    out = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        if p.is_symlink():
            out[rel] = "link:" + os.readlink(p)
        elif p.is_file():
            out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
        else:
            out[rel] = "dir"
    return out


@pytest.fixture
def ws(tmp_path, monkeypatch):
    """A workspace: a tree file, a data folder, a treeinfer-looking run folder, a logger CSV."""
    home = tmp_path / "home"  # outside the workspace: matplotlib's caches land there
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setenv("TREEINFER_JAX_CACHE", "off")
    tmp_path = tmp_path / "ws"
    tmp_path.mkdir()
    monkeypatch.chdir(tmp_path)
    shutil.copy(EXAMPLE_TREE, tmp_path / "tree.yaml")
    data = tmp_path / "data"
    data.mkdir()
    (data / "traj_000.csv").write_text("t,force,displacement\n0,0,0\n0.01,1,0.001\n")
    run = tmp_path / "run"
    run.mkdir()
    (run / OUTPUT_MARKER).write_text('{"writer": "treeinfer", "complete": true}\n')
    (run / "config.json").write_text(json.dumps({"versions": {"treeinfer": "0"}}))
    (run / "posterior.nc").write_bytes(b"\x89HDF precious")
    (tmp_path / "log.csv").write_text("time,force,displacement\n0,0,0\n1,1,1\n2,0,0\n")
    return tmp_path


def _refused(ws: Path, argv: list[str], capsys, *names: str) -> str:
    before = _snapshot(ws)
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert rc == 2, err
    for n in names:
        assert n in err, (n, err)
    after = _snapshot(ws)
    assert after == before, sorted(set(after) ^ set(before))  # nothing written, moved or staged
    return err


def _p(ws: Path, rel: str) -> str:
    return str(ws / rel)


# ---- every command, every case of the issue --------------------------------------------------
CASES = {
    "infer --prior-from R --out R --force": lambda w: [
        "infer", "--tree", _p(w, "tree.yaml"), "--data", _p(w, "data"), "--out", _p(w, "run"),
        "--prior-from", _p(w, "run"), "--force",
    ],
    "infer --out DATA --force": lambda w: [
        "infer", "--tree", _p(w, "tree.yaml"), "--data", _p(w, "data"), "--out", _p(w, "data"),
        "--force",
    ],
    "infer --out inside DATA": lambda w: [
        "infer", "--tree", _p(w, "tree.yaml"), "--data", _p(w, "data"), "--out",
        _p(w, "data/run"),
    ],
    "infer --out holding the tree --force": lambda w: [
        "infer", "--tree", _p(w, "tree.yaml"), "--data", _p(w, "data"), "--out", str(w),
        "--force",
    ],
    "infer --out = tree file": lambda w: [
        "infer", "--tree", _p(w, "tree.yaml"), "--data", _p(w, "data"), "--out",
        _p(w, "tree.yaml"),
    ],
    "calibrate --out holding its tree --force": lambda w: [
        "calibrate", "--tree", _p(w, "tree.yaml"), "--out", str(w), "--force",
    ],
    "calibrate --out = tree file": lambda w: [
        "calibrate", "--tree", _p(w, "tree.yaml"), "--out", _p(w, "tree.yaml"), "--force",
    ],
    "import-csv over its own source": lambda w: [
        "import-csv", _p(w, "log.csv"), "--out", str(w), "--force",
    ],
    "import-csv into a folder inside its source's name": lambda w: [
        "import-csv", _p(w, "data/traj_000.csv"), "--out", _p(w, "data"), "--force",
    ],
    "tree --from t.yaml --out t.yaml": lambda w: [
        "tree", "--from", _p(w, "tree.yaml"), "--out", _p(w, "tree.yaml"), "--force",
    ],
    "tree --mjcf = --from": lambda w: [
        "tree", "--from", _p(w, "tree.yaml"), "--out", _p(w, "t2.yaml"), "--mjcf",
        _p(w, "tree.yaml"), "--force",
    ],
    "simulate --out holding its tree --force": lambda w: [
        "simulate", "--tree", _p(w, "tree.yaml"), "--out", str(w), "--force",
    ],
    "simulate --out = --params-json": lambda w: [
        "simulate", "--tree", _p(w, "tree.yaml"), "--out", _p(w, "run/config.json"),
        "--params-json", _p(w, "run/config.json"), "--force",
    ],
    "predict --out RUN --force": lambda w: [
        "predict", "--run", _p(w, "run"), "--profile", "ramp:peak=1,ramp=0.1", "--duration",
        "0.2", "--out", _p(w, "run"), "--force",
    ],
    "predict --out = force CSV": lambda w: [
        "predict", "--run", _p(w, "run"), "--force-csv", _p(w, "data/traj_000.csv"), "--out",
        _p(w, "data/traj_000.csv"), "--force",
    ],
    "evaluate --out DATA --force": lambda w: [
        "evaluate", "--run", _p(w, "run"), "--data", _p(w, "data"), "--out", _p(w, "data"),
        "--force",
    ],
    "evaluate --out inside RUN": lambda w: [
        "evaluate", "--run", _p(w, "run"), "--data", _p(w, "data"), "--out", _p(w, "run/eval"),
    ],
    "suggest --out RUN --force": lambda w: [
        "suggest", "--run", _p(w, "run"), "--out", _p(w, "run"), "--force",
    ],
    "suggest --out inside RUN (not RUN/suggest)": lambda w: [
        "suggest", "--run", _p(w, "run"), "--out", _p(w, "run/mine"),
    ],
    "import-bag --out holding the bag --force": lambda w: [
        "import-bag", _p(w, "data/traj_000.csv"), "--out", _p(w, "data"), "--force",
    ],
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(CASES))
def test_output_overlapping_an_input_is_refused_before_any_work(ws, capsys, case):
    argv = CASES[case](ws)
    err = _refused(ws, argv, capsys, "an input of this command")
    # both paths are named: the output (--out, or --mjcf where that is the one) and the input
    flag = "--mjcf" if "--mjcf" in argv else "--out"
    assert argv[argv.index(flag) + 1] in err


def test_demo_refuses_the_home_folder_even_with_a_copied_marker(ws, capsys):
    home = Path(os.environ["HOME"])
    (home / ".ssh").mkdir()
    (home / ".ssh" / "id_ed25519").write_text("secret")
    (home / "config.json").write_text(json.dumps({"versions": {"treeinfer": "0"}}))  # look-alike
    (home / OUTPUT_MARKER).write_text("{}")  # a copied marker decides nothing destructive
    before = _snapshot(home)
    _refused(ws, ["demo", "--out", str(home), "--force"], capsys, str(home), "home folder")
    assert _snapshot(home) == before


def test_force_on_a_users_folder_is_refused_and_nothing_is_touched(ws, capsys):
    user = ws / "photos"
    user.mkdir()
    (user / "a.jpg").write_bytes(b"jpg")
    for argv in (
        ["simulate", "--tree", ws / "tree.yaml", "--out", user, "--force"],
        ["calibrate", "--tree", ws / "tree.yaml", "--out", user, "--force"],
        ["evaluate", "--run", ws / "run", "--data", ws / "data", "--out", user, "--force"],
        ["suggest", "--run", ws / "run", "--out", user, "--force"],
        ["demo", "--out", user, "--force"],
    ):
        _refused(ws, argv, capsys, str(user), "--force replaces only folders treeinfer wrote")


# ---- --force moves aside, never deletes ------------------------------------------------------
def test_force_over_a_look_alike_folder_keeps_every_file(tmp_path):
    """A user's folder holding a copy of a run's config.json and marker: --force may replace it
    as an output, but everything in it, a symlink out of it and what that points to, survives
    in NAME.old-<time>."""
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "keep.txt").write_text("outside")
    out = tmp_path / "out"
    (out / ".ssh").mkdir(parents=True)
    (out / ".ssh" / "id").write_text("secret")
    (out / "config.json").write_text(json.dumps({"versions": {"treeinfer": "0"}}))
    (out / OUTPUT_MARKER).write_text("{}")
    os.symlink(outside, out / "link")
    before = _snapshot(out)
    msgs = []
    with staged_output_dir(out, force=True, log=msgs.append) as stage:
        (stage / "new.txt").write_text("new")
    (old,) = tmp_path.glob("out.old-*")
    assert _snapshot(old) == before
    assert (outside / "keep.txt").read_text() == "outside"
    assert (out / "new.txt").read_text() == "new" and (out / "manifest.json").is_file()
    assert any(str(old) in m and "nothing was deleted" in m for m in msgs)


def test_force_never_recurses_into_the_old_folder(tmp_path, monkeypatch):
    """A mount point inside the replaced folder: publishing renames the folder; nothing walks
    or deletes inside it (the old code's rmtree emptied the mount)."""
    out = tmp_path / "run"
    with staged_output_dir(out) as stage:
        (stage / "a").write_text("1")
    (out / "mnt").mkdir()
    (out / "mnt" / "disk.img").write_text("data on another file system")
    calls = []
    monkeypatch.setattr(_io.shutil, "rmtree", lambda *a, **k: calls.append(a))
    with staged_output_dir(out, force=True) as stage:
        (stage / "a").write_text("2")
    assert calls == []
    (old,) = tmp_path.glob("run.old-*")
    assert (old / "mnt" / "disk.img").read_text() == "data on another file system"


def test_a_mount_point_as_the_output_is_refused(tmp_path, monkeypatch):
    out = tmp_path / "mnt"
    out.mkdir()
    (out / "x").write_text("x")
    real = os.path.ismount
    monkeypatch.setattr(os.path, "ismount", lambda p: Path(p) == out or real(p))
    with pytest.raises(OutputExistsError, match="mount point"):
        check_output_dir(out, force=True)


def test_an_empty_folder_is_reused_and_a_file_output_is_moved_aside(tmp_path):
    out = tmp_path / "empty"
    out.mkdir()
    with staged_output_dir(out) as stage:
        (stage / "r").write_text("r")
    assert not list(tmp_path.glob("empty.old-*"))  # nothing to keep
    f = tmp_path / "tree.yaml"
    f.write_text("mine")
    kept = move_aside(f, log=lambda m: None)
    assert kept.read_text() == "mine" and kept.name.startswith("tree.yaml.old-")
    assert move_aside(f) is None  # nothing there any more


def test_tree_force_keeps_the_previous_file(ws, capsys):
    out = ws / "t.yaml"
    out.write_text("my hand-edited tree\n")
    rc = main(["tree", "--from", str(ws / "tree.yaml"), "--out", str(out), "--force"])
    assert rc == 0, capsys.readouterr().err
    (old,) = ws.glob("t.yaml.old-*")
    assert old.read_text() == "my hand-edited tree\n"


def test_import_csv_force_keeps_the_replaced_trajectory(ws, capsys):
    out = ws / "imported"
    out.mkdir()
    (out / "log.csv").write_text("an earlier import the user edited by hand\n")
    rc = main(["import-csv", str(ws / "log.csv"), "--out", str(out), "--force"])
    assert rc == 0, capsys.readouterr().err
    (old,) = out.glob("log.csv.old-*")
    assert old.read_text() == "an earlier import the user edited by hand\n"


def test_refuse_overlap_follows_symlinks(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    os.symlink(data, tmp_path / "alias")
    with pytest.raises(OutputExistsError, match="is an input"):
        refuse_overlap(tmp_path / "alias", [data])
    refuse_overlap(tmp_path / "other", [data])  # unrelated: fine
    refuse_overlap(data / "suggest", [data], allow=[data / "suggest"])  # the one allowed place


# ---- infer --prior-from RUN checks RUN as every reader of a run does ---------------------------
def test_infer_prior_from_a_modified_run_is_refused_before_any_work(ws, capsys):
    """A prior run whose file changed after it was written (its manifest's checksum): exit 2
    naming the file and --allow-modified, before any data is read or anything written; and
    --allow-modified without --prior-from (infer reads no run then) is refused too."""
    from treeinfer.io.manifest import write_manifest

    prior = ws / "prior"
    prior.mkdir()
    (prior / "config.json").write_text(json.dumps({"command": "infer", "format": 1}))
    (prior / "particles.csv").write_text("particle,Kp[branch1]\n0,10.0\n")
    write_manifest(prior)
    (prior / OUTPUT_MARKER).write_text('{"writer": "treeinfer", "complete": true}\n')
    with (prior / "particles.csv").open("a") as f:
        f.write("1,11.0\n")  # an edit after the run
    base = ["infer", "--tree", ws / "tree.yaml", "--data", ws / "data", "--out", ws / "new"]
    err = _refused(ws, [*base, "--prior-from", prior], capsys, "--prior-from", "particles.csv")
    assert "--allow-modified" in err and "Traceback" not in err
    _refused(ws, [*base, "--allow-modified"], capsys, "--allow-modified", "--prior-from")
    # --resume takes the option from the interrupted run's config.json
    _refused(ws, ["infer", "--resume", ws / "new", "--allow-modified"], capsys, "--allow-modified")
