"""Run folders written before the application-layer refactor (issue 10) still load.

``tests/fixtures/run_main_2026-11-22/`` was written by main at ee21ba5:
``data/`` (``treeinfer simulate``, two_branch, 2 trajectories of 50 steps), ``run/`` (``treeinfer
infer --particles 4 --iterations 3 --checkpoint-every 1``; plots dropped) and
``interrupted.partial/`` (the same run stopped after the checkpoint of iteration 2).
Their config.json files hold absolute paths of the machine that wrote them; the copies made here
point the unhashed ``data.dir`` / ``checkpoint.dir`` / ``options.out`` at the copy (the hashed
options are left as written, so the recorded config hash and the checkpoint's stay valid).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from treeinfer.cli import main

FIXTURE = Path(__file__).resolve().parent / "fixtures" / "run_main_2026-11-22"


def _copy(tmp_path: Path) -> Path:
    root = tmp_path / "old"
    shutil.copytree(FIXTURE, root)
    for cfg_path in (root / "run" / "config.json", root / "interrupted.partial" / "config.json"):
        cfg = json.loads(cfg_path.read_text())
        cfg["data"]["dir"] = str(root / "data")
        out = root / ("run" if cfg_path.parent.name == "run" else "interrupted")
        cfg["options"]["out"] = str(out)
        cfg["checkpoint"]["dir"] = str(out) + ".partial"
        cfg_path.write_text(json.dumps(cfg, indent=2))
    return root


def test_old_run_predict_and_evaluate(tmp_path, capsys):
    root = _copy(tmp_path)
    rc = main(
        [
            "predict",
            "--run",
            str(root / "run"),
            "--profile",
            "ramp:peak=4,ramp=0.5",
            "--duration",
            "0.6",
            "--dt",
            "0.02",
            "--out",
            str(tmp_path / "pred"),
        ]
    )
    out, err = capsys.readouterr()
    assert rc == 0, err
    assert any((tmp_path / "pred").iterdir())
    rc = main(
        [
            "evaluate",
            "--run",
            str(root / "run"),
            "--data",
            str(root / "data"),
            "--out",
            str(tmp_path / "eval"),
            "--no-progress",
        ]
    )
    out, err = capsys.readouterr()
    assert rc == 0, err
    metrics = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert metrics, metrics


def test_old_interrupted_run_resumes(tmp_path, capsys):
    root = _copy(tmp_path)
    rc = main(["infer", "--resume", str(root / "interrupted"), "--no-progress"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    assert "from iteration 2" in err, err
    done = root / "interrupted"
    assert not (root / "interrupted.partial").exists()
    # the same seed and settings as the completed run: the same final particles
    new = np.loadtxt(done / "particles.csv", delimiter=",", skiprows=2, usecols=range(1, 5))
    old = np.loadtxt(root / "run" / "particles.csv", delimiter=",", skiprows=2, usecols=range(1, 5))
    np.testing.assert_allclose(new, old, rtol=1e-6)
