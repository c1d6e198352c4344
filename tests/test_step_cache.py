"""The accuracy-controlled step choice is kept on disk (keyed by the simulator's content hash,
the forces and the options) so a later process skips the step-doubling probes."""

from __future__ import annotations

import numpy as np

from treeinfer.sim import accuracy, make_simulator
from treeinfer.tree.generators import chain


def _tree():
    return chain(1, lengths=0.7, radii=0.03, angles_deg=0.0, base_position=(0.0, 0.0, 1.5),
                 base_pitch_deg=20.0, levels=1, name="c1")  # fmt: skip


def test_step_choice_is_cached_and_keyed(tmp_path, monkeypatch):
    monkeypatch.setenv("TREEINFER_JAX_CACHE", str(tmp_path))
    t = np.arange(40) * 0.01
    forces = (5.0 * np.clip(t / 0.2, 0, 1))[None]
    first = make_simulator(_tree(), obs_dt=0.01, forces=forces)
    files = list(tmp_path.rglob("steps/*.json"))
    assert len(files) == 1 and first.step_info["method"] == "accuracy"

    def boom(*a, **k):
        raise AssertionError("the probes ran although the choice was cached")

    monkeypatch.setattr(accuracy, "choose_substeps_for_accuracy", boom)
    again = make_simulator(_tree(), obs_dt=0.01, forces=forces)
    assert again.substeps == first.substeps and again.step_info == first.step_info
    assert again.fingerprint == first.fingerprint
    # other forces, or another tolerance: another key, the probes run
    called = []
    monkeypatch.setattr(
        accuracy, "choose_substeps_for_accuracy", lambda *a, **k: called.append(1) or (7, 1e-5)
    )
    other = make_simulator(_tree(), obs_dt=0.01, forces=2 * forces)
    assert called and other.substeps == 7
    make_simulator(_tree(), obs_dt=0.01, forces=forces, sim_tolerance=5e-5)
    assert len(called) == 2 and len(list(tmp_path.rglob("steps/*.json"))) == 3
    # a corrupt entry is recomputed, not trusted
    files[0].write_text("{not json")
    make_simulator(_tree(), obs_dt=0.01, forces=forces)
    assert len(called) == 3


def test_step_cache_off(tmp_path, monkeypatch):
    monkeypatch.setenv("TREEINFER_JAX_CACHE", "off")
    monkeypatch.setattr(accuracy, "choose_substeps_for_accuracy", lambda *a, **k: (5, 1e-5))
    sim = make_simulator(_tree(), obs_dt=0.01, forces=np.ones((1, 20)))
    assert sim.substeps == 5 and not list(tmp_path.rglob("*.json"))
