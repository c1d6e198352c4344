"""The default fit of SBC data set i in this process, its OWN log density (captured from resample-
move) at the truth and the draws, along the line from the draws' mean to the truth, and 200
sweeps of resample-move from half the cloud and half a cloud at the truth.
    python fitlp.py 51

Session 17 probe (issue 27), run from anywhere with the project importable; see README.md."""

# run the default fit on SBC data set i; capture its log density; compare truth vs draws
import sys
import tempfile

import numpy as np

ROOT = __import__("pathlib").Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))
from pathlib import Path

import sbc_default as S

import treeinfer.inference.resample_move as RM

cap = {}
orig = RM.resample_move


def wrap(log_density, draws, lw, lpd, n, **kw):
    cap["ld"] = log_density
    cap["draws"] = draws
    cap["lw"] = lw
    return orig(log_density, draws, lw, lpd, n, **kw)


RM.resample_move = wrap
from treeinfer.cli.infer_options import INFER_DEFAULTS
from treeinfer.examples import example_path
from treeinfer.runs import SimulatorCache
from treeinfer.tree import load_tree

tree_path = example_path("three_branch")
tree = load_tree(tree_path)
prior = S.GainPrior(tree, INFER_DEFAULTS)
cfg = dict(seed=0, sigma_x_range=(0.001, 0.004), n_traj=3, duration=3.0, dt=0.01, noise_force=0.05)
i = int(sys.argv[1])
truth, trajs, specs = S.draw_dataset(tree, prior, cfg, i)
wd = Path(tempfile.mkdtemp())
import inspect

src = inspect.getsource(S.run_sbc)
# write data the way the harness does
(wd / "data").mkdir(parents=True)
from treeinfer.data.trajectories import write_trajectory

for tr in trajs:
    write_trajectory(wd / "data" / f"{tr.source}.csv", tr)
post, summ = S.default_fit(tree_path, wd / "data", wd / "run", SimulatorCache())
lab = list(post.labels)
t = np.array([truth[k] for k in lab])
d = np.asarray(post.theta, float)
print("stop", summ.get("stop_reason"))
z = (t - d.mean(0)) / d.std(0)
print("z", np.round(z, 1))
if "ld" in cap:
    ld = cap["ld"]
    lt = ld(t[None])[0]
    ldr = ld(d)
    print(
        "fit lp: truth %.1f  draws median %.1f max %.1f  truth-median %.1f"
        % (lt, np.median(ldr), ldr.max(), lt - np.median(ldr))
    )
    np.savez(f"fit{i}.npz", t=t, d=d, lt=lt, ldr=ldr)
    m = d.mean(0)
    for a in [0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.2, 1.5]:
        x = m + a * (t - m)
        print("line a=%.1f lp-max %.1f" % (a, ld(x[None])[0] - ldr.max()))
    C = np.cov(d.T)
    dd = (t - m) @ np.linalg.solve(C, t - m)
    print("mahal^2 of truth in cloud", dd)
    # long RM from a mixture: half cloud, half around truth
    x0 = np.concatenate([d, t[None] + 0.3 * (d - m)])
    l0 = ld(x0)
    mv = orig(ld, x0, np.zeros(len(x0)), l0, 64, min_sweeps=200, max_sweeps=200)
    c = mv.chains
    print("mixed-start RM 200 sweeps: acc", mv.acceptance, "ind", mv.independent_acceptance)
    z2 = (t - c.mean(0)) / c.std(0)
    print(
        "z after", np.round(z2, 1), "lp chain median", np.median(mv.chain_log_density) - ldr.max()
    )
    half = len(c) // 2
    print(
        "first-half chains mean",
        np.round(c[:half].mean(0) - m, 3),
        "second half",
        np.round(c[half:].mean(0) - m, 3),
        "sd",
        np.round(d.std(0), 3),
    )
