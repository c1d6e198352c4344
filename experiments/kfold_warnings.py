"""Does ``treeinfer evaluate --kfold 3`` show each fold's convergence warnings? (issue 27)

The standard problem, every step a fresh ``treeinfer`` process as a user types it:

    treeinfer simulate --tree treeinfer/examples/three_branch.yaml --out W/train --n-traj 3 \\
        --seed 1 --noise-displacement 0.002 --noise-force 0.05
    treeinfer infer --tree T --data W/train --out W/run                  (no other flag)
    treeinfer evaluate --run W/run --data W/train --kfold 3 --out W/kfold

then, with ``--reference`` (the default), for every fold the same refit as a run of its own:
``treeinfer infer`` on that fold's training files (a folder of copies), whose summary.json's
``convergence_warnings`` are what ``infer`` would have shown. A fold passes when every one of
those warnings is among the fold's warnings in ``metrics.json`` AND printed by ``evaluate``
(same data, seed and settings give the same posterior, so the lists should match; the fold's
list adds how the refit ended). Records the wall time of each command (issue 27's target for
``evaluate --kfold 3``: < 10 min on a 2-core CPU).

    python experiments/kfold_warnings.py --out experiments/results/kfold_warnings_<machine>

Writes ``OUT/results.json`` (config, commands, per fold: warnings, the reference run's warnings,
what is missing, wall times) and ``OUT/results.md``; the work folder ``OUT/work`` (ignored by git).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TREE = ROOT / "treeinfer" / "examples" / "three_branch.yaml"


def _cli(args: list[str], log: Path) -> tuple[int, float, str]:
    """``python -m treeinfer ARGS`` from the repository root: (exit code, wall s, output)."""
    t0 = time.perf_counter()
    p = subprocess.run(
        [sys.executable, "-m", "treeinfer", *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    log.write_text(p.stdout)
    return p.returncode, time.perf_counter() - t0, p.stdout


def _kind(w: str) -> str:
    """A warning without its numbers: two refits of the same data on a GPU can differ in the
    last digits, not in what they warn about."""
    return re.sub(r"[-+]?\d[\d.,eE+-]*", "#", w)


def check(fold_warnings: list[str], printed: str, reference: list[str], fold: int) -> dict:
    """What of the reference run's warnings the fold leaves out of metrics.json / the output."""
    kinds = {_kind(w) for w in fold_warnings}
    missing_json = [w for w in reference if _kind(w) not in kinds]
    missing_printed = [w for w in fold_warnings if f"fold {fold}: {w}" not in printed]
    return {
        "missing_in_metrics_json": missing_json,
        "missing_in_output": missing_printed,
        "pass": not missing_json and not missing_printed,
    }


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "experiments/results/kfold_warnings")
    ap.add_argument("--k", type=int, default=3, help="folds (default 3)")
    ap.add_argument(
        "--no-reference", action="store_true", help="skip the per-fold reference runs of infer"
    )
    args = ap.parse_args(argv)
    work = args.out / "work"
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    wall: dict = {}
    simulate = ["simulate", "--tree", str(TREE), "--out", str(work / "train"), "--n-traj", "3"]
    simulate += ["--seed", "1", "--noise-displacement", "0.002", "--noise-force", "0.05"]
    rc, wall["simulate"], _ = _cli(simulate, work / "simulate.log")
    if rc:
        raise SystemExit(f"simulate failed (exit {rc}): {work / 'simulate.log'}")
    infer = [
        "infer",
        "--tree",
        str(TREE),
        "--data",
        str(work / "train"),
        "--out",
        str(work / "run"),
    ]
    rc_i, wall["infer"], _ = _cli(infer + ["--no-progress"], work / "infer.log")
    evaluate = ["evaluate", "--run", str(work / "run"), "--data", str(work / "train")]
    evaluate += ["--kfold", str(args.k), "--out", str(work / "kfold"), "--no-progress"]
    rc_e, wall["evaluate_kfold"], printed = _cli(evaluate, work / "evaluate.log")
    folds = []
    if rc_e == 0:
        m = json.loads((work / "kfold" / "metrics.json").read_text())
        for f in m["folds"]:
            rec = {
                "fold": f["fold"],
                "train": f["train"],
                "test": f["test"],
                "warnings": f.get("warnings"),
                "pct_outside": f["metrics"]["pct_outside"],
            }
            if not args.no_reference:
                d = work / f"fold{f['fold']}"
                (d / "train").mkdir(parents=True)
                for name in f["train"]:
                    shutil.copy(work / "train" / name, d / "train" / name)
                ref = ["infer", "--tree", str(TREE), "--data", str(d / "train")]
                ref += ["--out", str(d / "run"), "--no-progress", "--allow-poor-fit"]
                rc_r, wall[f"reference_infer_fold{f['fold']}"], _ = _cli(ref, d / "infer.log")
                s = json.loads((d / "run" / "summary.json").read_text()) if rc_r == 0 else {}
                rec["reference_warnings"] = s.get("convergence_warnings")
                rec["reference_stop_reason"] = s.get("stop_reason")
                rec.update(
                    check(
                        f.get("warnings") or [],
                        printed,
                        s.get("convergence_warnings") or [],
                        f["fold"],
                    )
                )
            folds.append(rec)
    res = {
        "config": {
            "commands": [
                "treeinfer " + " ".join(simulate),
                "treeinfer " + " ".join(infer),
                "treeinfer " + " ".join(evaluate),
            ],
            "machine": platform.platform(),
            "cpu_count": os.cpu_count(),
            "jax_platforms": os.environ.get("JAX_PLATFORMS"),
            "treeinfer_commit": subprocess.run(
                ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
            ).stdout.strip(),
            "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
        },
        "exit": {"infer": rc_i, "evaluate_kfold": rc_e},
        "wall_s": wall,
        "folds": folds,
        "pass": rc_e == 0 and all(f.get("pass", True) for f in folds),
    }
    lines = [
        f"# evaluate --kfold {args.k} on the standard problem: fold warnings",
        "",
        f"{res['config']['machine']}, {res['config']['cpu_count']} CPUs, commit "
        f"{res['config']['treeinfer_commit']}; wall: "
        + ", ".join(f"{k} {v:.0f} s" for k, v in wall.items()),
        "",
        "| fold | held out | % outside | fold warnings | reference run's warnings | missing |",
        "|---|---|---|---|---|---|",
    ]
    for f in folds:
        lines.append(
            f"| {f['fold']} | {', '.join(f['test'])} | {f['pct_outside']:.1f} | "
            f"{'; '.join(f['warnings'] or [])} | {'; '.join(f.get('reference_warnings') or [])} | "
            f"{'; '.join(f.get('missing_in_metrics_json', []) + f.get('missing_in_output', []))} |"
        )
    lines += ["", f"pass: {res['pass']}", ""]
    (args.out / "results.json").write_text(json.dumps(res, indent=2) + "\n")
    (args.out / "results.md").write_text("\n".join(lines))
    print("\n".join(lines))
    return res


if __name__ == "__main__":
    main()
