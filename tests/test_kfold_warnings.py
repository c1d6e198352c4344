"""``evaluate --kfold`` shows each fold's convergence warnings (issue 27: "did not show the
folds' convergence warnings"): a fold's refit must report what ``infer`` reports for a run, the
sampler's own convergence diagnostics (SVGD: mean log density still rising, KSD still falling;
MCMC: R-hat, ESS), not only how it ended, stuck particles and box edges.

A fake fold posterior whose NNSVGD trace is still climbing: the fold's warnings must hold every
warning :func:`treeinfer.runs.folder._diagnostics` gives that trace in a run's summary.json."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np

from treeinfer.runs import folder, folds


def _fold(n: int = 40, p: int = 8):
    rng = np.random.default_rng(0)
    positions = 0.1 * rng.normal(size=(n, p, 2))
    climbing = np.linspace(-900.0, -100.0, n)[:, None] + rng.normal(size=(n, p))  # not converged
    run = SimpleNamespace(
        stop_reason="max_iterations",
        settings={"n_iterations_done": n, "n_iterations": n, "start_iteration": 0},
        final_positions=positions[-1],
        final_state=SimpleNamespace(logdensity=climbing[-1]),
        trace_positions=positions,
        trace_logdensity=climbing,
        trace_iterations=np.arange(1, n + 1),
        diagnostics={},
        elapsed_s=1.0,
    )
    post = SimpleNamespace(run=run, theta=positions[-1], settings={}, log_density=climbing[-1])
    problem = SimpleNamespace(
        labels=("Kp[a]", "Kd[a]"), lower=np.full(2, -5.0), upper=np.full(2, 5.0)
    )
    return problem, post


def test_fold_warnings_include_the_samplers_convergence_warnings():
    problem, post = _fold()
    trace = {
        "positions": post.run.trace_positions,
        "log_density": post.run.trace_logdensity,
        "iterations": post.run.trace_iterations,
        "diagnostics": {},
        "resumed_from": None,
    }
    _, _, expected = folder._diagnostics("nnsvgd", trace, list(problem.labels))
    assert expected, "the climbing trace must trigger a convergence warning"
    warns = folds.fold_warnings(problem, post, {"sampler": "nnsvgd", "mcmc_warmup": 0.5})
    assert warns[0].startswith("ended by: max_iterations")
    for w in expected:
        assert w in warns


def test_a_fold_ended_by_resample_move_has_no_sampler_diagnostics():
    """A fold whose posterior came from the start pipeline (importance sampling, then
    resample-move) has one state, no sampler trace: no 'diagnostics unavailable' line (the
    evaluate --kfold 3 run of experiments/kfold_warnings.py printed one for fold 2)."""
    problem, post = _fold()
    one = post.run.trace_positions[-1:]
    post.run.trace_positions, post.run.trace_logdensity = one, post.run.trace_logdensity[-1:]
    post.run.trace_iterations = np.array([1])
    post.run.settings = {"start_iteration": 0}
    for stop in (
        "resample-move after importance sampling (Pareto k_hat 0.74): 12 Metropolis sweeps",
        "importance sampling (Pareto k_hat 0.53, effective sample size 438)",
    ):
        post.run.stop_reason = stop
        warns = folds.fold_warnings(problem, post, {"sampler": "nnsvgd", "mcmc_warmup": 0.5})
        assert warns[0] == f"ended by: {stop}"
        assert not any("diagnostics unavailable" in w for w in warns), warns
    post.run.stop_reason = "max_iterations"  # the check above is not vacuous: a sampler's stop
    warns = folds.fold_warnings(problem, post, {"sampler": "nnsvgd", "mcmc_warmup": 0.5})
    assert any("diagnostics unavailable" in w for w in warns), warns


def test_kfold_warnings_script_compares_warning_kinds():
    """``experiments/kfold_warnings.py``'s check: a reference warning counts as shown when the
    fold has the same warning up to its numbers, and every fold warning must be printed."""
    from experiments.kfold_warnings import check

    printed = "  fold 2: ended by: max_iterations\n  fold 2: KSD still falling: -71%\n"
    ok = check(
        ["ended by: max_iterations", "KSD still falling: -71%"],
        printed,
        ["KSD still falling: -70.2%"],
        2,
    )
    assert ok["pass"]
    bad = check(["ended by: max_iterations"], printed, ["Kd[a]: 27% beyond the box"], 2)
    assert bad["missing_in_metrics_json"] == ["Kd[a]: 27% beyond the box"] and not bad["pass"]
    unprinted = check(["ended by: max_iterations", "stuck"], printed, [], 2)
    assert unprinted["missing_in_output"] == ["stuck"]


def test_kfold_warnings_script_glue(tmp_path, monkeypatch):
    """The script's steps with the treeinfer commands replaced by stand-ins that write what the
    real ones write (metrics.json's folds, each reference run's summary.json): the result names
    the fold whose reference warning is missing, and the table is written."""
    import json

    from experiments import kfold_warnings as kw

    def fake_cli(args, log):
        log.write_text("")
        out = Path(args[args.index("--out") + 1])
        out.mkdir(parents=True, exist_ok=True)
        if args[0] == "simulate":
            for i in range(3):
                (out / f"traj_{i:03d}.csv").write_text("t\n")
        if args[0] == "evaluate":
            folds = [
                {
                    "fold": k,
                    "train": [f"traj_{j:03d}.csv" for j in range(3) if j != k - 1],
                    "test": [f"traj_{k - 1:03d}.csv"],
                    "metrics": {"pct_outside": 4.0},
                    "warnings": ["ended by: max_iterations after 200 iterations"],
                }
                for k in (1, 2, 3)
            ]
            (out / "metrics.json").write_text(json.dumps({"folds": folds}))
            printed = "".join(
                f"  fold {k}: ended by: max_iterations after 200 iterations\n" for k in (1, 2, 3)
            )
            return 0, 1.0, printed
        if args[0] == "infer" and "fold2" in str(out):  # only fold 2's own run warns
            (out / "summary.json").write_text(
                json.dumps({"convergence_warnings": ["KSD still falling: -88%"]})
            )
        elif args[0] == "infer":
            (out / "summary.json").write_text(json.dumps({"convergence_warnings": []}))
        return 0, 1.0, ""

    monkeypatch.setattr(kw, "_cli", fake_cli)
    res = kw.main(["--out", str(tmp_path)])
    assert not res["pass"]
    assert [f["pass"] for f in res["folds"]] == [True, False, True]
    assert res["folds"][1]["missing_in_metrics_json"] == ["KSD still falling: -88%"]
    assert (tmp_path / "results.md").read_text().count("| 2 |") == 1
