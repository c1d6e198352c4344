"""The notebooks execute top to bottom (nbclient, the engine nbmake drives).

``walkthrough.ipynb`` runs with ``TREEINFER_NOTEBOOK_SIZE=tiny`` (6 particles, 3 iterations): its
cost is MJX compiling the sampler and the predictions once (minutes cold on a loaded 2-core
machine, seconds with the persistent compilation cache warm). ``analysis.ipynb`` only reads
results: it runs on an empty results folder, on one holding a single study and on the
committed ``experiments/results``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"
RESULTS = ROOT / "experiments" / "results"
STUDIES = ("baselines", "nn_prior", "noise", "grasp")


def execute(name: str, monkeypatch, timeout: int = 1200, **env: str) -> nbformat.NotebookNode:
    """Run notebook ``name`` in a fresh kernel (which inherits this environment) from its folder."""
    for k, v in {"JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT), **env}.items():
        monkeypatch.setenv(k, v)
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    NotebookClient(
        nb, timeout=timeout, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOKS)}}
    ).execute()
    return nb


def outputs_text(nb) -> str:
    parts = []
    for cell in nb.cells:
        for out in cell.get("outputs", []):
            parts.append(out.get("text", ""))
            parts.extend(
                str(v)
                for k, v in out.get("data", {}).items()
                if k in ("text/plain", "text/markdown")
            )
    return "\n".join(parts)


def test_notebooks_are_stored_without_outputs():
    for path in NOTEBOOKS.glob("*.ipynb"):
        nb = nbformat.read(path, as_version=4)
        nbformat.validate(nb)
        assert all(
            not c.get("outputs") and c.get("execution_count") is None
            for c in nb.cells
            if c.cell_type == "code"
        ), path


@pytest.mark.slow  # compiles the sampler in a notebook kernel
def test_walkthrough_runs(monkeypatch):
    nb = execute("walkthrough.ipynb", monkeypatch, TREEINFER_NOTEBOOK_SIZE="tiny")
    text = outputs_text(nb)
    assert "size 'tiny'" in text
    assert "<mujoco" in text  # the MJCF of the tree
    assert "95% CI width" in text and "% of ground-truth points outside" in text
    images = [o for c in nb.cells for o in c.get("outputs", []) if "image/png" in o.get("data", {})]
    assert len(images) >= 4  # training data, trace, bands, pair plot


def test_analysis_runs_without_results(monkeypatch, tmp_path):
    nb = execute("analysis.ipynb", monkeypatch, timeout=300, TREEINFER_RESULTS_DIR=str(tmp_path))
    text = outputs_text(nb)
    assert "none" in text and "No results yet" in text


def test_analysis_runs_with_some_results(monkeypatch, tmp_path):
    present = [s for s in STUDIES if (RESULTS / s / "results.json").exists()]
    if not present:
        pytest.skip(
            "no committed results in experiments/results (run python experiments/<study>.py "
            "--size cpu)"
        )
    shutil.copytree(RESULTS / present[0], tmp_path / present[0])
    nb = execute("analysis.ipynb", monkeypatch, timeout=300, TREEINFER_RESULTS_DIR=str(tmp_path))
    text = outputs_text(nb)
    assert f"['{present[0]}']" in text
    nb = execute("analysis.ipynb", monkeypatch, timeout=300, TREEINFER_RESULTS_DIR=str(RESULTS))
    assert "| study | condition |" in outputs_text(nb)


@pytest.mark.slow
def test_real_data_runs(monkeypatch):
    """Raw 10 Hz logs (gf, mm, wrapping counter, offsets, noise) at three heights -> import_csv
    -> static-model inference from two heights -> evaluate at the third, at tiny size."""
    nb = execute("real_data.ipynb", monkeypatch, timeout=600, TREEINFER_NOTEBOOK_SIZE="tiny")
    text = outputs_text(nb)
    assert "size 'tiny'" in text
    assert "force: gf -> N" in text and "tare: subtracted" in text  # import_csv's report
    assert "exit code 0" in text and "damping (Kd): not identified" in text
    assert "% of the recorded points inside the 95% band" in text
    assert "cantilever" in text and "RMSE at 0.24 m" in text
    images = [o for c in nb.cells for o in c.get("outputs", []) if "image/png" in o.get("data", {})]
    assert len(images) >= 2  # the imported pushes, the held-out band
