"""SBC records fitted one after the other on this machine (session 15's clean-force check).

    python experiments/results/sbc_default_s15_cleanforce_local/sbcloc.py OUT NOISE_FORCE I [I ...]

Data set I is ``experiments/sbc_default.py``'s (seed 0, the full size's standard problem) with a
force noise of NOISE_FORCE N; each fit is the default command through ``default_fit``; one record
per data set is appended to ``OUT/records_w0.jsonl`` (the harness's format, ``--merge`` reads it).
"""

import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))

import treeinfer  # noqa: E402
from experiments.sbc_default import (  # noqa: E402
    SIZES,
    GainPrior,
    default_fit,
    draw_dataset,
    fit_record,
)
from treeinfer import runs  # noqa: E402
from treeinfer.cli.infer_options import INFER_DEFAULTS  # noqa: E402
from treeinfer.data.trajectories import write_trajectory  # noqa: E402
from treeinfer.tree import load_tree  # noqa: E402


def main(argv: list[str]) -> None:
    treeinfer.enable_compilation_cache()
    tree_path = ROOT / "treeinfer" / "examples" / "three_branch.yaml"
    tree = load_tree(tree_path)
    out, noise_force = Path(argv[0]), float(argv[1])
    out.mkdir(parents=True, exist_ok=True)
    cfg = dict(SIZES["full"], seed=0, sigma_x_range=[0.001, 0.004], noise_force=noise_force)
    prior, cache = GainPrior(tree, INFER_DEFAULTS), runs.SimulatorCache()
    work = Path(tempfile.mkdtemp(prefix="sbcloc_"))
    for i in map(int, argv[2:]):
        truth, trajs, _ = draw_dataset(tree, prior, cfg, i)
        d = work / f"ds{i}"
        (d / "data").mkdir(parents=True)
        for t in trajs:
            write_trajectory(d / "data" / f"{t.source}.csv", t)
        t0 = time.time()
        post, summary = default_fit(tree_path, d / "data", d / "run", cache)
        rec = {"index": i, "truth": truth, **fit_record(post, summary)}
        rec["wall_s"] = time.time() - t0
        with open(out / "records_w0.jsonl", "a", encoding="utf-8") as f:
            f.write(json.dumps(rec) + "\n")
        draws = np.asarray(rec["draws"])
        tv = np.array([truth[label] for label in rec["labels"]])
        z = np.round((tv - draws.mean(0)) / draws.std(0), 1)
        print(f"data set {i}: {rec['stop_reason'][:40]} z {z} wall {rec['wall_s']:.0f} s")
        shutil.rmtree(d, ignore_errors=True)


if __name__ == "__main__":
    main(sys.argv[1:])
