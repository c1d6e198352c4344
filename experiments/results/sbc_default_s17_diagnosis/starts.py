"""After the default fit of SBC data set i: Levenberg-Marquardt from the 64 best of 416 screen
points (two screen seeds); which starts end near the truth.
    python starts.py 51 134

Session 17 probe (issue 27), run from anywhere with the project importable; see README.md."""

import sys
import tempfile

import numpy as np

ROOT = __import__("pathlib").Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))
from pathlib import Path

import sbc_default as S

import treeinfer.inference.fast as FAST

cap = {}
orig = FAST.fast_posterior


def wrap(*a, **k):
    r = orig(*a, **k)
    cap.setdefault("fp", []).append((r, a, k))
    return r


FAST.fast_posterior = wrap
from treeinfer.cli.infer_options import INFER_DEFAULTS
from treeinfer.data.trajectories import write_trajectory
from treeinfer.examples import example_path
from treeinfer.inference.fast_fit import fit_map_batched
from treeinfer.inference.screen_points import screen_starts
from treeinfer.runs import SimulatorCache
from treeinfer.tree import load_tree

tree_path = example_path("three_branch")
tree = load_tree(tree_path)
prior = S.GainPrior(tree, INFER_DEFAULTS)
cfg = dict(seed=0, sigma_x_range=(0.001, 0.004), n_traj=3, duration=3.0, dt=0.01, noise_force=0.05)
cache = SimulatorCache()
for i in [int(a) for a in sys.argv[1:]]:
    cap.clear()
    truth, trajs, specs = S.draw_dataset(tree, prior, cfg, i)
    wd = Path(tempfile.mkdtemp())
    (wd / "data").mkdir(parents=True)
    for tr in trajs:
        write_trajectory(wd / "data" / f"{tr.source}.csv", tr)
    post, summ = S.default_fit(tree_path, wd / "data", wd / "run", cache)
    lab = list(post.labels)
    t = np.array([truth[k] for k in lab])
    d = np.asarray(post.theta, float)
    z = (t - d.mean(0)) / d.std(0)
    fp, a, k = cap["fp"][-1]
    ev = fp.evaluator
    problem = ev.problem
    print(
        i,
        "n fast_posterior calls",
        len(cap["fp"]),
        "starts given",
        [kk.get("starts") is not None for _, _, kk in cap["fp"]],
        flush=True,
    )
    ld = ev.log_density
    lt = ld(t[None])[0]
    best = ld(d).max()
    print(i, "z", np.round(z, 1), "truth-best draw %.1f" % (lt - best), flush=True)
    R = tree.n_inferred
    for seed in (0, 1):
        st, pts = screen_starts(ev, problem, 416, 64, seed, None)
        fit = fit_map_batched(ev, st, 30, 1e-4)
        vals = -np.asarray(fit.values)
        fin = np.asarray(fit.finals)
        near = [
            (j, vals[j] - best)
            for j in range(len(fin))
            if np.abs(fin[j, : 2 * R] - t[: 2 * R]).max() < 0.3
        ]
        print(
            "  seed",
            seed,
            "its",
            fit.iterations,
            "best final - best draw %.1f" % (np.nanmax(vals) - best),
            "starts ending near truth (rank, lp-best):",
            [(j, round(v, 1)) for j, v in near][:8],
            flush=True,
        )
