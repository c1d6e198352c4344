# local SBC records: python sbcloc.py OUTDIR NOISE_FORCE i0 i1 ...
import sys, json, time, shutil, numpy as np
from pathlib import Path
sys.path.insert(0, "/work/main")
from experiments.sbc_default import draw_dataset, GainPrior, SIZES, default_fit, fit_record
from treeinfer.cli.infer_options import INFER_DEFAULTS
from treeinfer.tree import load_tree
from treeinfer.data.trajectories import write_trajectory
from treeinfer import runs
import treeinfer
treeinfer.enable_compilation_cache()
tp = Path("/work/main/treeinfer/examples/three_branch.yaml"); tree = load_tree(tp)
out = Path(sys.argv[1]); nf = float(sys.argv[2]); out.mkdir(parents=True, exist_ok=True)
cfg = dict(SIZES["full"], seed=0, sigma_x_range=[0.001, 0.004], noise_force=nf)
gp = GainPrior(tree, INFER_DEFAULTS); cache = runs.SimulatorCache()
for i in map(int, sys.argv[3:]):
    truth, trajs, specs = draw_dataset(tree, gp, cfg, i)
    d = Path(f"/tmp/lead15/sbcloc_work/ds{i}"); shutil.rmtree(d, ignore_errors=True); (d / "data").mkdir(parents=True)
    for t in trajs: write_trajectory(d / "data" / f"{t.source}.csv", t)
    t0 = time.time()
    post, summary = default_fit(tp, d / "data", d / "run", cache)
    rec = {"index": i, "truth": truth, **fit_record(post, summary), "wall_s": time.time() - t0}
    with open(out / "records_w0.jsonl", "a") as f: f.write(json.dumps(rec) + "\n")
    dr = np.asarray(rec["draws"]); tv = np.array([truth[l] for l in rec["labels"]])
    print("DS", i, rec["stop_reason"][:40], "z", np.round((tv - dr.mean(0)) / dr.std(0), 1), "wall", round(rec["wall_s"]), flush=True)
