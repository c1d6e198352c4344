"""A cold process on a NEW data set compiles nothing once the persistent cache holds a run of
the same shape bucket (issue 15 item 4): `treeinfer infer --init importance` on data set A,
then a fresh process on data set B (other forces and displacements, another accurate step, the
same number of pulls, a length in the same bucket); and `treeinfer warmup` then `infer`.

XLA compilations are counted by :mod:`treeinfer.sim.compile_stats` (JAX's monitoring events: a
backend compile not served by the persistent cache), through ``benchmarks.compile_probe``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from treeinfer.examples import example_path

ROOT = Path(__file__).resolve().parent.parent
TREE = str(example_path("two_branch"))
INFER = ["--particles", "16", "--init", "importance"]


def _env(cache: Path) -> dict:
    path = os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])
    return {**os.environ, "JAX_PLATFORMS": "cpu", "TREEINFER_JAX_CACHE": str(cache),
            "PYTHONPATH": path}  # fmt: skip


def _run(args, cache: Path, report: Path | None = None) -> dict | None:
    cmd = [sys.executable, "-m"]
    cmd += ["treeinfer"] if report is None else ["benchmarks.compile_probe", "--report",
                                                 str(report), "--"]  # fmt: skip
    r = subprocess.run(cmd + args, cwd=ROOT, env=_env(cache), capture_output=True, text=True)
    assert r.returncode in (0, 4), r.stderr[-3000:]
    return None if report is None else json.loads(report.read_text())


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Data sets A (71 samples) and B (67 samples, other seed): one bucket, [2, 80]."""
    work = tmp_path_factory.mktemp("cold")
    out = {}
    for name, seed, duration in (("a", 1, "0.7"), ("b", 2, "0.66")):
        out[name] = work / f"data_{name}"
        _run(["simulate", "--tree", TREE, "--out", str(out[name]), "--n-traj", "2", "--seed",
              str(seed), "--duration", duration, "--noise-displacement", "0.002"],
             work / "sim_cache")  # fmt: skip
    return out


def _infer(data: Path, out: Path, cache: Path, report: Path) -> dict:
    args = ["infer", "--tree", TREE, "--data", str(data), "--out", str(out), "--no-progress",
            "--allow-poor-fit", *INFER]  # fmt: skip
    return _run(args, cache, report)


@pytest.mark.slow  # fresh processes that run infer
def test_a_new_data_set_of_the_bucket_compiles_nothing(data, tmp_path):
    cache = tmp_path / "cache"
    a = _infer(data["a"], tmp_path / "run_a", cache, tmp_path / "a.json")
    assert a["xla_compiles"] > 10  # the counter sees compilations (an empty cache)
    exports = sorted(cache.rglob("*.jaxexport"))  # the step check's and the fit's programs
    assert len(exports) >= 2, exports
    b = _infer(data["b"], tmp_path / "run_b", cache, tmp_path / "b.json")
    # B's accurate step differs from A's, yet it traced no stored program anew
    assert sorted(cache.rglob("*.jaxexport")) == exports
    steps = [json.loads((tmp_path / f"run_{n}" / "config.json").read_text())["problem"]
             for n in "ab"]  # fmt: skip
    assert steps[0]["shape_bucket"] == steps[1]["shape_bucket"] == [2, 80]
    assert steps[0]["substeps"] != steps[1]["substeps"]  # what the stored programs leave out
    assert b["cache_hits"] > 10 and b["xla_compiles"] == 0, b["compiled"]


@pytest.mark.slow  # fresh processes that run infer
def test_warmup_fills_the_cache_for_a_field_run(data, tmp_path):
    cache = tmp_path / "cache"
    r = subprocess.run(
        [sys.executable, "-m", "treeinfer", "warmup", "--tree", TREE, "--n-traj", "2",
         "--steps", "75", "--", *INFER],
        cwd=ROOT, env=_env(cache), capture_output=True, text=True,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    assert "compiled " in r.stdout and f"cache folder: {cache}" in r.stdout, r.stdout
    b = _infer(data["b"], tmp_path / "run_b", cache, tmp_path / "b.json")
    assert b["cache_hits"] > 10 and b["xla_compiles"] == 0, b["compiled"]


def test_warmup_refuses_options_it_sets_itself(tmp_path, capsys):
    from treeinfer.cli import main

    rc = main(["warmup", "--tree", TREE, "--", "--data", str(tmp_path)])
    assert rc == 2 and "infer option --data" in capsys.readouterr().err
    rc = main(["warmup", "--tree", TREE, "--steps", "2"])
    assert rc == 2 and "--steps" in capsys.readouterr().err
