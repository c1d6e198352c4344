"""After the default fit of SBC data set i: Levenberg-Marquardt from its best draw with one
stiffness raised and another lowered by 0.35 or 0.7 log units (parent/child trade starts).
    python trade.py 51 134 20 48

Session 17 probe (issue 27), run from anywhere with the project importable; see README.md."""

import itertools
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
    cap.setdefault("fp", []).append(r)
    return r


FAST.fast_posterior = wrap
from treeinfer.cli.infer_options import INFER_DEFAULTS
from treeinfer.data.trajectories import write_trajectory
from treeinfer.examples import example_path
from treeinfer.inference.fast_fit import fit_map_batched
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
    fp = cap["fp"][-1]
    ev = fp.evaluator
    ld = ev.log_density
    lt = ld(t[None])[0]
    ldr = ld(d)
    print(
        i,
        "z",
        np.round(z, 1),
        "fit lp truth-max draw %.1f" % (lt - ldr.max()),
        summ.get("stop_reason")[:50],
        flush=True,
    )
    m = d[np.argmax(ldr)]
    R = tree.n_inferred
    starts = []
    for a, b in itertools.combinations(range(R), 2):
        for dl in (0.35, -0.35, 0.7, -0.7):
            s = m.copy()
            s[a] += dl
            s[b] -= dl
            starts.append(s)
    starts = np.array(starts)
    fit = fit_map_batched(ev, starts, 30, 1e-4)
    vals = -np.asarray(fit.values)
    fin = np.asarray(fit.finals)
    best = ldr.max()
    for v, f, s in sorted(zip(vals, fin, starts), key=lambda x: -x[0])[:6]:
        print(
            "   final lp-best %.1f" % (v - best),
            "dist to truth (gains) %.2f" % np.abs(f[: 2 * R] - t[: 2 * R]).max(),
            "to mode %.2f" % np.abs(f[: 2 * R] - m[: 2 * R]).max(),
            flush=True,
        )
