"""Calibration of the amortised posterior (issue 31 §2): expected coverage and SBC ranks of
`treeinfer amortise`'s flow on held-out simulated data sets.

Trains a model (:func:`treeinfer.amortised.train`) for a tree and a layout of pulls, then draws
``sets`` held-out data sets from the same prior, noise model and pull family with another seed
and, for each, ``draws`` draws of the flow (:func:`treeinfer.amortised.expected_coverage`):
the share of data sets whose truth lies in the central 50/80/90/95% intervals (nominal: the
level) and the chi-square p-value of the truth's rank among the draws (uniform when
calibrated). The flow alone is measured: the answer `infer --amortised` gives before its check
against the simulator. Target (issue 31): coverage within 2 points of nominal.

    JAX_PLATFORMS=cpu python experiments/amortised_calibration.py --size tiny   # ~20 s, CPU
    JAX_PLATFORMS=cpu python experiments/amortised_calibration.py --size cpu    # ~40 s, CPU
    JAX_PLATFORMS=cpu python experiments/amortised_calibration.py --size cpu --tree two_branch \
        --check 10                                                     # 2 joints, CPU, minutes
    # one H200 (each well within its 10-minute limit: --gpu sets --budget-s 480, the training
    # starting no epoch after 390 s and the checks none after what is left; progress on stderr)
    python experiments/amortised_calibration.py --gpu --tree two_branch \
        --out experiments/results/amortised_full_two_branch_s13
    # the session-12 model (box space, shapes summary) on the same 5000 held-out sets
    python experiments/amortised_calibration.py --gpu --tree two_branch \
        --model experiments/results/amortised_full_two_branch/model \
        --out experiments/results/amortised_full_two_branch_5000
    python experiments/amortised_calibration.py --gpu --tree two_branch --check 5 \
        --model experiments/results/amortised_full_two_branch/model \
        --out experiments/results/amortised_full_two_branch_check

``--check N`` also runs the on-the-spot check of ``infer --amortised`` against the real
simulator-based posterior (``make_problem``: the run's likelihood, force-noise term and
priors) on N recordings drawn from the training distribution (truth from the prior, noise from
the noise model, a quarter with a clean force) and on N outside it (forces ten times the
trained peaks; the displacement 80 ms behind the force): the share answered without fallback
(target: all in-distribution ones) and the share that falls back (target: all others), with
each one's Pareto k_hat, effective sample size, refinement rounds and check time.

Writes ``experiments/results/amortised_<size>_<tree>/`` (or ``--out``): results.json (the
config, the training report, coverage, ranks' p-values, latency), results.md, and the model
(model.msgpack, model.json), staged and published whole.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

SIZES = {
    # 1-joint chain, 2 short pulls: a smoke size whose flow is already near nominal
    "tiny": dict(
        layout=dict(n_pulls=2, duration=0.5),
        sims=2048,
        epochs=40,
        width=32,
        layers=3,
        sets=200,
        draws=200,
    ),
    "cpu": dict(
        layout=dict(n_pulls=3, duration=1.0),
        sims=8192,
        epochs=100,
        width=48,
        layers=4,
        sets=200,
        draws=400,
    ),
    # the defaults of `treeinfer simulate` (8 pulls of 3 s): a GPU's job, sized for one
    # command of under 10 minutes on an H100/H200 (large chunks and batches: the rollouts and
    # the flow's steps fill the device; early stop on the held-out tenth)
    "full": dict(
        layout=dict(),
        sims=200_000,
        # session 13: 300 epochs, patience 20 (the session-12 model ran all of its 150 without
        # an early stop: still improving); the --gpu budget stops starting epochs at 390 s
        epochs=300,
        width=128,
        layers=6,
        # 5000 held-out sets: at 500 a perfectly calibrated posterior shows a largest gap of
        # 3.6 points (median; 5.6 at the 95th percentile) over 5 columns x 4 levels, so the
        # target of 2 points was not resolvable; at 5000, 1.1 (1.8)
        sets=5000,
        draws=1000,
        chunk=4096,
        batch=1024,
        patience=20,
        embedding=32,  # 8 pulls of 5 columns' worth: twice the default summary
    ),
}


# a GPU command may run 10 minutes: the training stops starting epochs RESERVE_S before the
# budget, left for the held-out simulations, the flow's draws on them and the save
GPU_BUDGET_S = 480.0
RESERVE_S = 90.0


def _tree(name: str):
    import treeinfer as ti
    from treeinfer.tree.generators import chain

    if name == "chain1":
        return chain(1, lengths=0.7, radii=0.03, name="chain1")
    if Path(name).suffix in (".yaml", ".yml", ".json"):
        return ti.load_tree(name)
    return ti.load_tree(ti.example_path(name))


def _markdown(res: dict) -> str:
    cov = res["coverage"]
    levels = list(next(iter(cov.values())))
    lines = [
        f"# Amortised posterior calibration: {res['config']['tree']} ({res['config']['size']})",
        "",
        f"{res['n_sets']} held-out data sets, {res['n_draws']} flow draws each; trained on "
        f"{res['training']['n_datasets']} simulations in {res['training']['training_s']:.0f} s "
        f"({res['training']['epochs_run']} epochs"
        + (", stopped at the time budget" if res["training"].get("stopped_at_deadline") else "")
        + f"). Posterior latency (warm, this machine): "
        f"{res['latency_ms']:.2f} ms.",
        "",
        "| parameter | " + " | ".join(f"{float(lv):.0%}" for lv in levels) + " | SBC chi2 p |",
        "|---|" + "---|" * (len(levels) + 1),
    ]
    for lab, row in cov.items():
        cells = " | ".join(f"{row[lv]:.3f}" for lv in levels)
        lines.append(f"| {lab} | {cells} | {res['chi2_p'][lab]:.3g} |")
    null = res.get("null_max_gap")
    lines += [
        "",
        f"Largest |coverage - nominal|: {res['max_coverage_gap']:.3f}"
        + (
            f" (a perfectly calibrated posterior on {res['n_sets']} sets: median "
            f"{null['median']:.3f}, 95th percentile {null['p95']:.3f})"
            if null
            else ""
        ),
        "",
    ]
    if "mean_log_q_truth" in res:
        lines += [
            f"Mean log q(truth | data) on the held-out sets: {res['mean_log_q_truth']:.3f} "
            "(theta units; higher: sharper, for the same sets only).",
            "",
        ]
    if res.get("checks"):
        from experiments._amortised_checks import checks_markdown

        lines += checks_markdown(res["checks"])
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", choices=SIZES, default="tiny")
    ap.add_argument("--gpu", action="store_true", help="the GPU's size: --size full")
    ap.add_argument(
        "--check",
        type=int,
        default=0,
        metavar="N",
        help="also check the amortised start against the simulator on N in-distribution and N "
        "out-of-distribution recordings",
    )
    ap.add_argument(
        "--tree", default="chain1", help="chain1 (a 1-joint chain), an example name or a tree file"
    )
    ap.add_argument("--seed", type=int, default=0, help="training seed (held-out: seed + 1000)")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument(
        "--space",
        choices=("probit", "box"),
        default="probit",
        help="the flow's coordinates (probit: the prior a standard normal, "
        "treeinfer.amortised.space; box: the models before session 13)",
    )
    ap.add_argument(
        "--summary",
        choices=("dynamics", "shapes"),
        default="dynamics",
        help="the per-pull features (shapes: the models before session 13)",
    )
    ap.add_argument(
        "--model", type=Path, default=None, help="measure this trained model (no training)"
    )
    ap.add_argument("--force", action="store_true")
    ap.add_argument("--sims", type=int, default=None, help="training simulations (the size's)")
    ap.add_argument("--epochs", type=int, default=None, help="most epochs (the size's)")
    ap.add_argument("--sets", type=int, default=None, help="held-out data sets (the size's)")
    ap.add_argument(
        "--budget-s",
        type=float,
        default=None,
        help="whole-command seconds: the flow's training starts no epoch after this less "
        f"{RESERVE_S:g} s for the calibration and the save (default with --gpu: {GPU_BUDGET_S:g})",
    )
    ap.add_argument(
        "--check-budget-s",
        type=float,
        default=None,
        help="stop starting new --check recordings after this many seconds (every kind in turn; "
        "default: what --budget-s leaves)",
    )
    args = ap.parse_args(argv)
    if args.gpu:
        args.size = "full"
        if args.budget_s is None:
            args.budget_s = GPU_BUDGET_S
    t_start = time.perf_counter()

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - t_start:7.1f} s] {msg}", file=sys.stderr, flush=True)

    import treeinfer as ti
    from treeinfer.amortised import (
        AmortiseConfig,
        PullLayout,
        TrainConfig,
        expected_coverage,
        save,
        train,
    )
    from treeinfer.io.atomic import staged_output_dir
    from treeinfer.io.provenance import versions

    ti.enable_compilation_cache()
    size = dict(SIZES[args.size])
    for key, v in (("sims", args.sims), ("epochs", args.epochs), ("sets", args.sets)):
        if v is not None:
            size[key] = v
    tree = _tree(args.tree)
    cfg = AmortiseConfig(
        PullLayout(**size["layout"]),
        TrainConfig(
            simulations=size["sims"],
            epochs=size["epochs"],
            width=size["width"],
            flow_layers=size["layers"],
            seed=args.seed,
            chunk=size.get("chunk", 256),
            batch_size=size.get("batch", 256),
            patience=size.get("patience", 10),
            embedding=size.get("embedding", 16),
            space=args.space,
            summary=args.summary,
        ),
    )
    name = f"amortised_{args.size}_{Path(args.tree).stem}"
    out = args.out or ROOT / "experiments" / "results" / name
    t0 = time.perf_counter()
    if args.model:  # a model trained before (this script's, or `treeinfer amortise`'s)
        from treeinfer.amortised import load

        am = load(args.model)
        am.check_tree(tree, f"--tree {args.tree}")
        cfg = am.config
    else:
        log(f"training: {size['sims']} simulations, at most {size['epochs']} epochs")
        deadline = None if args.budget_s is None else t_start + args.budget_s - RESERVE_S
        am = train(tree, cfg, log=log, progress=args.size == "full", deadline=deadline)
        if am.meta["training"]["stopped_at_deadline"]:
            log(f"training stopped at the time budget ({args.budget_s:g} s for the command)")
    t1 = time.perf_counter()
    log(f"calibration: {size['sets']} held-out data sets, {size['draws']} draws each")
    res = expected_coverage(am, tree, size["sets"], size["draws"], seed=args.seed + 1000, log=log)
    res["calibration_s"] = round(time.perf_counter() - t1, 1)
    log(f"calibration done in {res['calibration_s']} s")
    gaps = [abs(v - float(lv)) for row in res["coverage"].values() for lv, v in row.items()]
    checks = None
    if args.check:
        from experiments._amortised_checks import run_checks

        budget = args.check_budget_s
        if budget is None and args.budget_s is not None:  # what the command has left, less 30 s
            budget = max(0.0, args.budget_s - (time.perf_counter() - t_start) - 30.0)
        checks = run_checks(am, tree, args.check, seed=args.seed + 2000, log=log, budget_s=budget)
    res = {
        "config": {
            "size": args.size,
            "tree": args.tree,
            "seed": args.seed,
            "held_out_seed": args.seed + 1000,
            **cfg.to_json(),
            "sets": size["sets"],
            "draws": size["draws"],
            "command": "python experiments/amortised_calibration.py "
            + " ".join(sys.argv[1:] if argv is None else argv),
        },
        "training": am.meta["training"],
        "versions": versions(),
        **{k: v for k, v in res.items() if k != "ranks"},
        "max_coverage_gap": float(max(gaps)),
        **({"checks": checks} if checks else {}),
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    with staged_output_dir(out, args.force, "results") as stage:
        (stage / "results.json").write_text(json.dumps(res, indent=1) + "\n")
        (stage / "results.md").write_text(_markdown(res))
        save(am, stage / "model")
    print(_markdown(res))
    print(f"wrote {out}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
