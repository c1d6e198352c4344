"""``experiments/default_calibration.py``'s summary (issue 27's independent-reference study) on
hand-made run records whose figures are known: per-case and pooled coverage, the
Clopper-Pearson rate per parameter, std / CRB over the identified parameters only, the clean
runs' target, and the merge of seed chunks run in separate calls. No fit is run here (the
study itself is the lead's GPU command; ``--size tiny`` is its smoke run)."""

from __future__ import annotations

import json

import pytest

from experiments import default_calibration as dc


def _run(case, seed, inside, truths, ratios, ident, clean=False, exit_=0, verdict="ok", stuck=0):
    return {
        "case": case,
        "seed": seed,
        "clean": clean,
        "infer": {"exit": exit_, "wall_s": 10.0 + seed},
        "evaluate": {"wall_s": 3.0},
        "verdict": verdict,
        "stop_reason": "importance",
        "stragglers": stuck,
        "convergence_warnings": ["w"] if stuck else [],
        "test_pct_inside": inside,
        "test_band": "predictive",
        "truth_in_interval": truths,
        "std_over_crb_force_noise": ratios,
        "std_over_crb": ratios,
        "identified": ident,
    }


RUNS = [
    _run("chain2", 0, 95.0, {"a": True, "b": True}, {"a": 1.2, "b": 9.0}, {"a": True, "b": False}),
    _run("chain2", 1, 90.0, {"a": True, "b": False}, {"a": 2.5, "b": 8.0}, {"a": True, "b": False}),
    _run("chain3", 0, 96.0, {"c": True}, {"c": 0.4}, {"c": True}, stuck=2),
    _run("chain3", 0, 100.0, {"c": True}, {}, {}, clean=True),
    _run(
        "chain2", 0, 100.0, {"a": True, "b": False}, {}, {}, clean=True, exit_=4, verdict="poor_fit"
    ),
]


def test_summary_per_case_and_pooled():
    s = dc.summarise(RUNS)
    pooled, c2, c3 = s["pooled"], s["per_case"]["chain2"], s["per_case"]["chain3"]
    assert (pooled["n_runs"], c2["n_runs"], c3["n_runs"]) == (3, 2, 1)
    assert pooled["test_pct_inside"]["runs_in_target_93_97"] == 2
    assert c2["test_pct_inside"]["mean"] == pytest.approx(92.5)
    assert (pooled["truth_in_interval"]["k"], pooled["truth_in_interval"]["n"]) == (4, 5)
    assert c2["truth_in_interval_per_parameter"]["b"]["k"] == 1
    # only identified parameters enter std / CRB: 1.2, 2.5, 0.4 (not the prior-bound 9 and 8);
    # within 2x means either way: 2.5 is too wide, 0.4 over-confident
    cr = pooled["std_over_crb_force_noise"]
    assert (cr["identified_parameters"], cr["all_parameters"]) == (3, 5)
    assert cr["max_identified"] == pytest.approx(2.5)
    assert cr["share_identified_within_2x"] == pytest.approx(1 / 3)
    assert cr["share_identified_below_half"] == pytest.approx(1 / 3)
    assert pooled["stuck_particles"] == 2 and pooled["runs_with_convergence_warnings"] == 1
    clean = {c["case"]: c for c in s["clean"]}
    assert clean["chain3"]["target_met"] and not clean["chain2"]["target_met"]
    assert clean["chain2"]["poor_fit"]
    md = dc.markdown({"summary": s, "runs": RUNS, "config": _config()})
    assert "| pooled | 3 |" in md and "| chain3 | 1 |" in md


def _config():
    return {
        "size": "tiny",
        "infer_command": "x",
        "treeinfer_commit": "abc",
        "cpu_count": 2,
        "machine": "m",
        "date_utc": "d",
    }


def test_merge_of_seed_chunks(tmp_path):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps({"config": _config(), "runs": RUNS[:2]}))
    # the second chunk re-ran chain2 seed 1 (replaces the first one's) and added chain3
    again = {**RUNS[1], "test_pct_inside": 94.0}
    b.write_text(json.dumps({"config": _config(), "runs": [again, *RUNS[2:]]}))
    res = dc.merge([a, b], tmp_path / "merged")
    assert len(res["runs"]) == 5
    assert res["summary"]["per_case"]["chain2"]["test_pct_inside"]["min"] == 94.0
    assert (tmp_path / "merged" / "results.json").exists()
    assert json.loads((tmp_path / "merged" / "results.json").read_text())["config"]["merged_from"]


def test_help_names_the_chunking_options(capsys):
    with pytest.raises(SystemExit):
        dc.main(["--help"])
    text = capsys.readouterr().out
    for flag in ("--seed-start", "--budget-s", "--merge"):
        assert flag in text


@pytest.mark.slow
def test_tiny_study_end_to_end(tmp_path):
    """One noisy chain2 run through the CLI (infer + evaluate as fresh processes): the record
    has the test coverage, the truths, std / CRB with the identified flags, and the summary."""
    res = dc.main(["--size", "tiny", "--cases", "chain2", "--out", str(tmp_path)])
    (run,) = res["runs"]
    assert run["infer"]["exit"] in (0, 4)
    assert 0.0 <= run["test_pct_inside"] <= 100.0
    assert set(run["identified"]) == set(run["std_over_crb_force_noise"])
    assert all(v > 0 for v in run["crb_log_std_force_noise"].values())
    assert res["summary"]["per_case"]["chain2"]["n_runs"] == 1
    assert (tmp_path / "results.md").exists()


def test_clean_only_runs_the_noise_free_runs_alone(tmp_path, monkeypatch):
    calls = []

    def fake_run(case, work, clean, infer_args):
        calls.append((case, clean))
        return _run(case, 0, 100.0, {"a": True}, {}, {}, clean=clean)

    monkeypatch.setattr(dc, "one_run", fake_run)
    monkeypatch.setattr(dc, "make_case", lambda name, *a: name)
    dc.main(["--seeds", "1", "--clean-only", "--out", str(tmp_path)])
    assert calls == [("chain2", True), ("chain3", True)]
    with pytest.raises(SystemExit):
        dc.main(["--clean-only", "--no-clean", "--out", str(tmp_path)])
