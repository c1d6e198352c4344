"""Output folders never lose data (issue 14, item 4): --force protection, rescue of a finished
result when the final rename fails, stale staging folders, disk errors naming the file."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from treeinfer.errors import ConfigError, OutputExistsError
from treeinfer.io import atomic as _io
from treeinfer.io.atomic import (
    OUTPUT_MARKER,
    OutputWriteError,
    atomic_save,
    atomic_write_bytes,
    check_output_dir,
    clean_stale_staging,
    find_staging,
    is_treeinfer_output,
    staged_output_dir,
)
from treeinfer.io.manifest import MANIFEST, write_manifest
from treeinfer.runs.integrity import (
    check_partial,
    load_npz,
    record_checksums,
    validate_checkpoint_file,
    validate_run_config,
    validate_summary,
    verify_run,
)

ROOT = Path(__file__).resolve().parents[1]


def _write(out: Path, text: str = "new", **kw) -> Path:
    with staged_output_dir(out, **kw) as stage:
        (stage / "result.txt").write_text(text)
    return out


def test_staged_folder_is_marked_and_replaceable(tmp_path):
    out = _write(tmp_path / "run")
    assert (out / "result.txt").read_text() == "new"
    marker = json.loads((out / OUTPUT_MARKER).read_text())
    assert marker == {"writer": "treeinfer", "complete": True}
    assert is_treeinfer_output(out)
    with pytest.raises(OutputExistsError, match="pass --force"):
        _write(out, "second")
    _write(out, "second", force=True)
    assert (out / "result.txt").read_text() == "second"
    assert find_staging(out) == []


def test_force_never_replaces_a_foreign_folder(tmp_path):
    data = tmp_path / "mine"
    data.mkdir()
    (data / "pull1.csv").write_text("time,force,displacement\n")
    with pytest.raises(OutputExistsError, match="replaces only folders treeinfer wrote"):
        _write(data, force=True)
    assert (data / "pull1.csv").exists() and not (data / "result.txt").exists()
    empty = tmp_path / "empty"
    empty.mkdir()
    _write(empty, force=True)  # an empty folder is fine
    assert (empty / "result.txt").exists()


def test_legacy_treeinfer_folder_counts_as_ours(tmp_path):
    old = tmp_path / "oldrun"
    old.mkdir()
    (old / "config.json").write_text(json.dumps({"versions": {"treeinfer": "0.1"}}))
    assert is_treeinfer_output(old)
    (old / "config.json").write_text(json.dumps({"versions": {"other": "1"}}))
    assert not is_treeinfer_output(old)


def test_force_never_replaces_the_commands_inputs(tmp_path):
    data = _write(tmp_path / "s_copy")  # a treeinfer-written data folder (has the marker)
    (data / "pull1.csv").write_text("x")
    for inp in (data, data / "pull1.csv"):
        with pytest.raises(OutputExistsError, match="an input of this command"):
            check_output_dir(data, True, "run", inputs=[inp])
    with pytest.raises(OutputExistsError, match="contains an input"):
        _write(tmp_path, force=True, inputs=[data / "pull1.csv"])
    assert (data / "pull1.csv").read_text() == "x"


def test_mount_point_refused_before_work(tmp_path, monkeypatch):
    out = tmp_path / "mnt"
    out.mkdir()
    monkeypatch.setattr(_io.os.path, "ismount", lambda p: Path(p) == out)
    with pytest.raises(OutputExistsError, match="mount point"):
        check_output_dir(out)


@pytest.mark.parametrize("existing", [False, True])
def test_failed_final_rename_keeps_the_finished_result(tmp_path, monkeypatch, existing):
    out = tmp_path / "run"
    if existing:
        _write(out, "previous")
    real = os.replace

    def busy(src, dst):
        if Path(dst) == out or (existing and Path(src) == out):
            raise OSError(errno.EBUSY, "Device or resource busy", str(dst))
        return real(src, dst)

    monkeypatch.setattr(_io.os, "replace", busy)
    with pytest.raises(
        OutputWriteError, match="Device or resource busy.*nothing is lost: it is complete in"
    ) as ei:
        _write(out, "finished", force=True)
    kept = Path(str(ei.value).split("complete in ")[1].split(";")[0])
    assert kept.is_dir() and (kept / "result.txt").read_text() == "finished"
    assert kept.name == f"run.complete-{os.getpid()}"
    if existing:  # the previous result is untouched
        assert (out / "result.txt").read_text() == "previous"
    assert find_staging(out) == []


def test_error_inside_removes_stage_and_keeps_previous(tmp_path):
    out = _write(tmp_path / "run", "previous")
    with pytest.raises(RuntimeError), staged_output_dir(out, force=True) as stage:
        (stage / "half.txt").write_text("x")
        raise RuntimeError("boom")
    assert (out / "result.txt").read_text() == "previous" and find_staging(out) == []


def _killed_writer(out: Path, complete: bool) -> None:
    """A child process killed (SIGKILL) inside staged_output_dir, or between the two renames."""
    code = f"""
import os, signal
from pathlib import Path
from treeinfer import _io
out = Path({str(out)!r})
if {complete!r}:
    real = _io.os.replace
    calls = []
    def die_on_second(src, dst):  # of the publish step's renames (the first writes manifest.json)
        calls.append(1)
        if len(calls) == 3:
            os.kill(os.getpid(), signal.SIGKILL)
        return real(src, dst)
    _io.os.replace = die_on_second
with _io.staged_output_dir(out, force=True) as stage:
    (stage / "result.txt").write_text("killed run")
    if not {complete!r}:
        os.kill(os.getpid(), signal.SIGKILL)
"""
    r = subprocess.run([sys.executable, "-c", code], check=False, cwd=ROOT, capture_output=True)
    assert r.returncode == -9, r.stderr.decode()


def test_sigkill_mid_write_leaves_staging_that_the_next_run_removes(tmp_path):
    out = _write(tmp_path / "run", "previous")
    _killed_writer(out, complete=False)
    assert len(find_staging(out)) == 1
    msgs = clean_stale_staging(out)
    assert any("removed a staging folder" in m for m in msgs)
    assert find_staging(out) == [] and (out / "result.txt").read_text() == "previous"


def test_sigkill_between_renames_recovers_the_finished_result(tmp_path):
    out = _write(tmp_path / "run", "previous")
    _killed_writer(out, complete=True)
    assert not out.exists()  # the kill fell between moving the old one away and the new one in
    msgs = clean_stale_staging(out)
    assert any("recovered the finished result" in m for m in msgs), msgs
    assert (out / "result.txt").read_text() == "killed run"
    assert find_staging(out) == []
    (old,) = tmp_path.glob("run.old-*")  # --force kept the previous result, never deleted it
    assert (old / "result.txt").read_text() == "previous"


def test_displaced_old_result_is_put_back(tmp_path):
    out = _write(tmp_path / "run", "previous")
    os.replace(out, tmp_path / ".run.999999999.old")  # a dead PID
    msgs = clean_stale_staging(out)
    assert any("put back the previous result" in m for m in msgs)
    assert (out / "result.txt").read_text() == "previous"


def test_live_process_staging_is_left_alone(tmp_path):
    out = tmp_path / "run"
    live = tmp_path / f".run.{os.getppid()}.abcd.staging"
    live.mkdir()
    msgs = clean_stale_staging(out)
    assert live.is_dir() and "left alone" in msgs[0]


def test_disk_full_names_the_file(tmp_path, monkeypatch):
    target = tmp_path / "posterior.nc"

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(_io.os, "fsync", full)
    with pytest.raises(
        OutputWriteError,
        match=r"posterior.nc: cannot write \(No space left on device; the disk is full\)",
    ):
        atomic_write_bytes(target, b"x" * 10)
    assert list(tmp_path.iterdir()) == []


def test_writer_error_on_a_full_disk_names_the_file(tmp_path, monkeypatch):
    target = tmp_path / "posterior.nc"

    class Usage:
        free = 0

    monkeypatch.setattr(_io.shutil, "disk_usage", lambda p: Usage())
    pattern = "posterior.nc: cannot write .*HDF error.*probably full"
    with pytest.raises(OutputWriteError, match=pattern), atomic_save(target):
        raise RuntimeError("NetCDF: HDF error")
    # with free space the writer's own error is a bug, passed through unchanged
    Usage.free = 1 << 30
    with pytest.raises(RuntimeError, match="HDF error"), atomic_save(target):
        raise RuntimeError("NetCDF: HDF error")


# ---- run-folder integrity (issue 14, items 5 and 7) ------------------------------------------


def _fake_run(tmp_path: Path) -> tuple[Path, dict]:
    run = tmp_path / "run"
    run.mkdir()
    (run / "tree.yaml").write_text("branches:\n  - {name: child, length: 0.6}\n")
    (run / "posterior.nc").write_bytes(b"\x89HDF\r\n" + bytes(range(200)))
    (run / "particles.csv").write_text("particle,Kp[child]\n0,10.0\n")
    # as save_run and publish_staged write it: config.json promises the manifest of every file
    config = {"integrity": {**record_checksums(run), "manifest": MANIFEST}}
    (run / "config.json").write_text(json.dumps(config))
    write_manifest(run)
    (run / ".treeinfer-output").write_text('{"writer": "treeinfer", "complete": true}\n')
    return run, config


def test_verify_run_accepts_an_untouched_run(tmp_path):
    run, config = _fake_run(tmp_path)
    assert set(config["integrity"]["files"]) == {"tree.yaml", "posterior.nc", "particles.csv"}
    assert verify_run(run, config) == []


def test_edited_tree_is_refused_or_noted(tmp_path):
    run, config = _fake_run(tmp_path)
    (run / "tree.yaml").write_text("branches:\n  - {name: child, length: 0.9}\n")  # 0.6 -> 0.9 m
    with pytest.raises(ConfigError, match=r"tree.yaml was edited after the run.*--allow-modified"):
        verify_run(run, config)
    notes = verify_run(run, config, allow_modified=True)
    assert len(notes) == 1 and "tree.yaml was edited" in notes[0]


@pytest.mark.parametrize("damage", ["garbage", "truncate", "delete"])
def test_damaged_or_missing_posterior_is_refused(tmp_path, damage):
    run, config = _fake_run(tmp_path)
    p = run / "posterior.nc"
    if damage == "garbage":
        p.write_bytes(b"not a netcdf file")
    elif damage == "truncate":
        p.write_bytes(p.read_bytes()[:50])
    else:
        p.unlink()
    pattern = "posterior.nc is missing" if damage == "delete" else "posterior.nc is damaged"
    with pytest.raises(ConfigError, match=pattern):
        verify_run(run, config)


def test_run_without_checksums_gets_a_note(tmp_path):
    run, _ = _fake_run(tmp_path)
    (run / MANIFEST).unlink()  # a run from before checksums and manifests
    notes = verify_run(run, {"format": 1})
    assert "no checksums recorded" in notes[0]


def test_run_from_before_manifests_loads_with_a_note(tmp_path):
    run, config = _fake_run(tmp_path)
    (run / MANIFEST).unlink()
    del config["integrity"]["manifest"]
    (notes,) = verify_run(run, config)
    assert "before manifests" in notes and "config.json and summary.json could not be" in notes


def test_removed_manifest_of_a_new_run_is_damage(tmp_path):
    run, config = _fake_run(tmp_path)
    (run / MANIFEST).unlink()
    with pytest.raises(ConfigError, match="manifest.json is missing"):
        verify_run(run, config)


@pytest.mark.parametrize("name", ["manifest.json", ".treeinfer-output"])
def test_an_edited_manifest_or_marker_is_damage(tmp_path, name):
    run, _ = _fake_run(tmp_path)
    with open(run / name, "a") as f:
        f.write(" ")  # still valid JSON: only the bytes tell
    with pytest.raises(ConfigError, match=name):
        verify_run(run, None)


@pytest.mark.parametrize("name", ["config.json", "particles.csv"])
def test_manifest_catches_an_edited_config_or_any_file(tmp_path, name):
    run, _ = _fake_run(tmp_path)
    with open(run / name, "a") as f:
        f.write(" ")
    with pytest.raises(ConfigError, match=f"{name} was edited after the run"):
        verify_run(run, None)
    (note,) = verify_run(run, None, allow_modified=True)
    assert "--allow-modified" in note and name in note


GOOD_CONFIG = {
    "format": 1,
    "command": "infer",
    "options": {
        "sampler": "nnsvgd",
        "particles": 8,
        "iterations": 4,
        "seed": 0,
        "kT": 0.05,
        "max_unstable_share": 0.1,
        "checkpoint_every": 2,
        "grasp_fraction": None,
    },
    "problem": {"kT": 0.05, "obs_dt": 0.01, "substeps": 2, "backend": "fused"},
    "tree_dict": {},
    "config_hash": "ab",
    "sampler": {},
    "data": {"dir": "/d", "files": [{"name": "a.csv", "sha256": "00"}]},
}


@pytest.mark.parametrize(
    "edit, pattern",
    [
        (lambda c: c.pop("problem"), r"field 'problem': missing"),
        (
            lambda c: c["problem"].__setitem__("kT", "0.05"),
            r"field 'problem.kT': expected a positive number, got '0.05'",
        ),
        (
            lambda c: c["options"].__setitem__("particles", True),
            r"field 'options.particles': expected an integer >= 1",
        ),
        (lambda c: c["data"]["files"].append("x"), r"field 'data.files\[1\]'"),
        (
            lambda c: c["problem"].__setitem__("substeps", 0),
            r"field 'problem.substeps': expected an integer >= 1",
        ),
    ],
)
def test_validate_run_config(edit, pattern):
    import copy

    assert validate_run_config(GOOD_CONFIG, "run/config.json", resumable=True)
    bad = copy.deepcopy(GOOD_CONFIG)
    edit(bad)
    with pytest.raises(ConfigError, match=r"run/config.json, " + pattern):
        validate_run_config(bad, "run/config.json", resumable=True)


def test_validate_summary_indices():
    assert validate_summary({"unstable_particles": [0, 7]}, "s.json", 8)
    with pytest.raises(
        ConfigError,
        match=r"s.json, field 'unstable_particles\[1\]': 99 is not a particle index in \[0, 8\)",
    ):
        validate_summary({"unstable_particles": [0, 99]}, "s.json", 8)
    with pytest.raises(ConfigError, match="unstable_particles\\[0\\]': -1"):
        validate_summary({"unstable_particles": [-1]}, "s.json", 8)
    with pytest.raises(ConfigError, match="fit.status"):
        validate_summary({"fit": {"status": "great"}}, "s.json", 8)


def test_empty_and_foreign_checkpoints(tmp_path):
    import numpy as np

    ck = tmp_path / "checkpoint.npz"
    ck.write_bytes(b"")
    with pytest.raises(ConfigError, match="checkpoint is empty"):
        validate_checkpoint_file(ck)
    with pytest.raises(ConfigError, match=r"checkpoint.npz: .* is empty"):
        load_npz(ck, "checkpoint")
    ck.write_bytes(b"garbage!")
    with pytest.raises(ConfigError, match="not a checkpoint"):
        validate_checkpoint_file(ck)
    np.savez(ck, a=np.arange(3))
    ck.write_bytes(ck.read_bytes()[:40])  # truncated zip
    validate_checkpoint_file(ck)  # looks like a zip ...
    with pytest.raises(ConfigError, match="unreadable checkpoint"):  # ... but np.load fails cleanly
        load_npz(ck, "checkpoint")


def test_check_partial_says_why(tmp_path):
    import copy

    partial = tmp_path / "RUN.partial"
    partial.mkdir()
    (partial / "tree.yaml").write_text("x")
    assert "has no config.json" in check_partial(partial)
    (partial / "config.json").write_text(json.dumps(copy.deepcopy(GOOD_CONFIG)))
    assert check_partial(partial) is None
    (partial / "checkpoint.npz").write_bytes(b"")
    assert "checkpoint is empty" in check_partial(partial)
