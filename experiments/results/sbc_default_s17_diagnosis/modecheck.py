"""The mode check (treeinfer.inference.mode_check) on SBC data sets fitted again on this box:
per data set the truths' z-scores against the particles, the check's record and its warnings.
    python modecheck.py OUT.jsonl 51 134 48 72 109 13 57 65 8

Session 17 probe (issue 27); see README.md."""

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))
import sbc_default as S  # noqa: E402

from treeinfer.cli.infer_options import INFER_DEFAULTS  # noqa: E402
from treeinfer.data.trajectories import write_trajectory  # noqa: E402
from treeinfer.examples import example_path  # noqa: E402
from treeinfer.runs import SimulatorCache  # noqa: E402
from treeinfer.tree import load_tree  # noqa: E402

tree_path = example_path("three_branch")
tree = load_tree(tree_path)
prior = S.GainPrior(tree, INFER_DEFAULTS)
cfg = dict(seed=0, sigma_x_range=(0.001, 0.004), n_traj=3, duration=3.0, dt=0.01, noise_force=0.05)
cache = SimulatorCache()
out = Path(sys.argv[1])
for i in [int(a) for a in sys.argv[2:]]:
    truth, trajs, specs = S.draw_dataset(tree, prior, cfg, i)
    wd = Path(tempfile.mkdtemp())
    (wd / "data").mkdir(parents=True)
    for tr in trajs:
        write_trajectory(wd / "data" / f"{tr.source}.csv", tr)
    t0 = time.perf_counter()
    post, summ = S.default_fit(tree_path, wd / "data", wd / "run", cache)
    wall = time.perf_counter() - t0
    t = np.array([truth[k] for k in post.labels])
    d = np.asarray(post.theta, float)
    z = (t - d.mean(0)) / d.std(0)
    check = dict(post.run.settings.get("missed_modes") or {})
    rec = {
        "index": i,
        "z": np.round(z, 2).tolist(),
        "max_abs_z_gains": float(np.abs(z[:-1]).max()),
        "flagged": int(check.get("n_flagged", 0)),
        "warnings": check.get("warnings", []),
        "nats_above_best": check.get("nats_above_best"),
        "wall_s": wall,
        "stop_reason": summ.get("stop_reason"),
    }
    with open(out, "a") as f:
        f.write(json.dumps(rec) + "\n")
    print(i, "max|z| %.1f" % rec["max_abs_z_gains"], "flagged", rec["flagged"], flush=True)
