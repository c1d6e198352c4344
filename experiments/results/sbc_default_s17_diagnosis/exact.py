"""The posterior rows of an SBC folder against the truth under an independent density: the accurate
simulator, J exact at each point (MODE=exact), J fixed at the posterior mean (MODE=fixed), or
the fit's substeps (MODE=fitsim).
    MODE=exact python exact.py sbc_default_s16_final 51 20 72 48 109

Session 17 probe (issue 27), run from anywhere with the project importable; see README.md."""

import glob
import gzip
import json
import math
import sys

import numpy as np

ROOT = __import__("pathlib").Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))
import sbc_default as S

from treeinfer.cli.infer_options import INFER_DEFAULTS
from treeinfer.examples import example_path
from treeinfer.model.force_noise import force_jacobian
from treeinfer.sim import simulate
from treeinfer.sim.synthetic import simulate_batch
from treeinfer.tree import load_tree

D = sys.argv[1]
import os

MODE = os.environ.get("MODE", "exact")
recs = {}
for f in glob.glob(str(ROOT / "experiments/results" / D / "records_w*.jsonl.gz")):
    for line in gzip.open(f, "rt"):
        r = json.loads(line)
        recs[r["index"]] = r
tree = load_tree(example_path("three_branch"))
prior = S.GainPrior(tree, INFER_DEFAULTS)
cfg = dict(seed=0, sigma_x_range=(0.001, 0.004), n_traj=3, duration=3.0, dt=0.01, noise_force=0.05)
R = tree.n_inferred


def exact_lp(sim, th, sx, F, X, sF=0.05, Jref=None):
    roll = simulate(sim, np.exp(th[:R])[None], np.exp(th[R:])[None], F)
    res = X - np.asarray(roll.tau[0], float)
    J = force_jacobian(sim, th, F, check=False, keep=False) if Jref is None else Jref
    lp = 0.0
    for b in range(len(F)):
        C = sF**2 * J[b] @ J[b].T + sx**2 * np.eye(F.shape[1])
        s, ld = np.linalg.slogdet(C)
        lp += -0.5 * (ld + res[b] @ np.linalg.solve(C, res[b]) + F.shape[1] * math.log(2 * math.pi))
    return lp


for i in [int(a) for a in sys.argv[2:]]:
    r = recs[i]
    truth, trajs, specs = S.draw_dataset(tree, prior, cfg, i)
    lab = r["labels"]
    t = np.array([truth[k] for k in lab])
    d = np.array(r["draws"])
    F = np.stack([tr.force for tr in trajs])
    X = np.stack([tr.displacement for tr in trajs])
    _, sim = simulate_batch(tree, np.exp(t[:R]), np.exp(t[R : 2 * R]), F, 0.01)
    m = d.mean(0)
    z = (t - m) / d.std(0)
    import dataclasses

    if len(sys.argv) > 0 and MODE == "fitsim":
        sim = dataclasses.replace(sim, substeps=int(r["substeps"]))
    Jm = force_jacobian(sim, m[:-1], F, check=False, keep=False) if MODE == "fixed" else None
    sx = math.exp(m[-1])
    lpt = exact_lp(sim, t[:-1], sx, F, X, Jref=Jm) + float(prior.log_density(t[None, :-1])[0])
    # exact lp at a few draws: mean and 8 draws
    idx = np.random.default_rng(0).choice(len(d), 8, replace=False)
    lpd = [
        exact_lp(sim, d[k, :-1], sx, F, X, Jref=Jm) + float(prior.log_density(d[k : k + 1, :-1])[0])
        for k in idx
    ]
    lpm = exact_lp(sim, m[:-1], sx, F, X, Jref=Jm) + float(prior.log_density(m[None, :-1])[0])
    print(
        i,
        "maxz %.1f" % np.abs(z[:-1]).max(),
        "z",
        np.round(z, 1),
        "exact lp: truth-mean %.1f" % (lpt - lpm),
        "truth - draws median %.1f max %.1f" % (lpt - np.median(lpd), lpt - np.max(lpd)),
        r["stop_reason"][:30],
        flush=True,
    )
