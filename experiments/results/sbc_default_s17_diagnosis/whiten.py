"""Residuals at the TRUTH of SBC data set i whitened by sigma_x^2 I + sigma_F^2 J J^T with J exact
at the truth (and without the force term): mean square and lag-1 autocorrelation per pull.
    python whiten.py 0 1 2 3

Session 17 probe (issue 27), run from anywhere with the project importable; see README.md."""

import math
import sys

import numpy as np

ROOT = __import__("pathlib").Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "experiments"))
import sbc_default as S

from treeinfer.examples import example_path
from treeinfer.model.force_noise import force_jacobian
from treeinfer.sim.synthetic import simulate_batch
from treeinfer.tree import load_tree

tree = load_tree(example_path("three_branch"))
from treeinfer.cli.infer_options import INFER_DEFAULTS

prior = S.GainPrior(tree, INFER_DEFAULTS)
cfg = dict(seed=0, sigma_x_range=(0.001, 0.004), n_traj=3, duration=3.0, dt=0.01, noise_force=0.05)
for i in [int(a) for a in sys.argv[1:]]:
    truth, trajs, specs = S.draw_dataset(tree, prior, cfg, i)
    lab = list(truth)
    th = np.array([truth[k] for k in lab[:-1]])
    sx = math.exp(truth["sigma_x"])
    r_ = tree.n_inferred
    F = np.stack([t.force for t in trajs])
    X = np.stack([t.displacement for t in trajs])
    roll, sim = simulate_batch(tree, np.exp(th[:r_]), np.exp(th[r_:]), F, 0.01)
    xs = np.asarray(roll.tau[0], float)
    res = X - xs
    J = force_jacobian(sim, th, F)
    out = []
    for sF in [0.05, 0.0]:
        chi = []
        ac = []
        for b in range(len(F)):
            C = sF**2 * J[b] @ J[b].T + sx**2 * np.eye(len(F[b]))
            L = np.linalg.cholesky(C)
            w = np.linalg.solve(L, res[b])
            chi.append(np.mean(w**2))
            ac.append(np.corrcoef(w[:-1], w[1:])[0, 1])
        out.append((sF, np.round(chi, 2), np.round(ac, 2)))
    fv = np.array([np.trace(0.05**2 * J[b] @ J[b].T) / len(F[b]) for b in range(len(F))])
    print(
        i,
        "sx %.2fmm" % (sx * 1e3),
        "force-var/sx2",
        np.round(fv / sx**2, 2),
        "substeps",
        sim.substeps,
        out,
        flush=True,
    )
