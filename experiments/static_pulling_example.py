"""A worked static tree pulling test (issue 30, section 2): a winch cable at a height and angle,
a force ramp, inclinometers at the stem base and at two heights; the quasi-static model
(stiffness only) and the full dynamic model fitted to the same angle channels.

The tree (``OUT/tree.yaml``): a 12 m stem as a chain of three hinged links, ``root`` (0-1 m:
its spring lumps the root-soil rotation), ``lower`` (1-4 m) and ``upper`` (4-12 m), upright,
bending in the x-z plane; wood 900 kg/m^3. The cable is slung at 8 m (0.5 of ``upper``) and
runs 20 deg below the horizontal to the anchor (``pull: {direction: [cos 20, 0, -sin 20]}``).
Inclinometers (one axis, the tilt in the pull plane: rotation about y) at 0.5 m (on ``root``),
2 m (``lower``) and 6 m (``upper``), and a draw-wire sensor on the sling (its displacement
along the cable: the "grasp-point" displacement every treeinfer pull records).

The data come from the independent planar reference (:class:`treeinfer.sim.planar_reference.
PlanarTree`: Lagrange's equations integrated by scipy, no MuJoCo or treeinfer simulator code),
the full dynamics at the true stiffness *and* damping, sampled at 10 Hz, with realistic noise:

* tilts: white noise 0.003 deg (5e-5 rad), then rounded to the inclinometer's 0.001 deg;
* force: the load cell's 10 N quanta (rounding only; ``infer``'s default force-noise term,
  estimated from the recording, is on for the static model and off for the dynamic one);
* displacement: 1 mm white noise (a draw-wire sensor).

Two pulls: ``train/pull_2kN.csv`` (ramp to 2 kN in 10 s, hold 3 s, release in 2 s) for
inference, ``test/pull_3kN.csv`` (ramp to 3 kN in 12 s, hold 3 s, release in 2 s: a larger
load than any in training) held out. Every noise scale is inferred (the default).

Each model's posterior is the start pipeline's generic path for a problem with channels
(:func:`treeinfer.inference.start_pipeline.model_importance`: MAP + Laplace, adaptive importance
sampling with PSIS weights; resample-move where the weights are not trusted), i.e. what
``treeinfer infer`` does before any sampler. Reported per model: the truths inside their 95%
intervals (static: Kp only; damping is not identified by a slow pull), and the held-out pull's
coverage by the 95% predictive band, per inclinometer and for the displacement.

    nice python experiments/static_pulling_example.py            # ~20 min on 2 busy cores
    nice python experiments/static_pulling_example.py --cli      # + the CLI commands (docs)

Writes ``OUT/results.json``, ``OUT/results.md``, ``OUT/heldout_bands.png`` (and copies it to
``docs/img/static_pulling_example.png``), the tree and data folders (``OUT/tree.yaml``,
``OUT/data/{train,test}``) that ``docs/pulling_tests.md``'s commands use.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

OUT = ROOT / "experiments" / "results" / "static_pulling_example"
CABLE_DEG = 20.0
_CX, _CZ = math.cos(math.radians(CABLE_DEG)), -math.sin(math.radians(CABLE_DEG))  # pull direction
TRUTH = {
    "kp": {"root": 3.0e6, "lower": 8.0e6, "upper": 4.0e6},  # N m/rad
    "kd": {"root": 3.0e4, "lower": 5.0e4, "upper": 2.0e4},  # N m s/rad
}
CLINOS = {
    "clino_0.5m": ("root", 0.5),
    "clino_2m": ("lower", 1.0 / 3.0),
    "clino_6m": ("upper", 0.25),
}  # fmt: skip  (link, fraction: heights 0.5, 2, 6 m)
PULLS = {  # name: (folder, peak N, ramp s, hold s, release s)
    "pull_2kN.csv": ("train", 2000.0, 10.0, 3.0, 2.0),
    "pull_3kN.csv": ("test", 3000.0, 12.0, 3.0, 2.0),
}
DT = 0.1
NOISE = {"tilt_rad": 5e-5, "tilt_quantum_deg": 1e-3, "force_quantum_N": 10.0,
         "displacement_m": 1e-3}  # fmt: skip
CONFIG = {
    "tree": "OUT/tree.yaml (written by this script)",
    "cable_angle_deg": CABLE_DEG,
    "sling": "upper link at 0.5 (8 m)",
    "truth": TRUTH,
    "clinos": {k: {"link": v[0], "fraction": v[1]} for k, v in CLINOS.items()},
    "pulls": {
        k: {"folder": v[0], "peak_N": v[1], "ramp_s": v[2], "hold_s": v[3], "release_s": v[4]}
        for k, v in PULLS.items()
    },  # fmt: skip
    "dt": DT,
    "noise": NOISE,
    "data": "PlanarTree (Lagrange + scipy), full dynamics at the true Kp and Kd",
    "posterior": "model_importance (MAP + Laplace + adaptive importance sampling, PSIS); "
    "resample-move where the weights are not trusted; the dynamic fit also starts from the "
    "static posterior's Kp and noise scales with Kd across its box",
}

TREE_YAML = f"""\
# A standing tree for a static pulling test (experiments/static_pulling_example.py)
name: pulling-test-stem
base:
  position: [0.0, 0.0, 0.0]
  pitch_deg: 90.0             # upright
  yaw_deg: 0.0                # bending in the x-z plane, x toward the anchor
gravity: [0.0, 0.0, -9.81]
density: 900.0                # kg/m^3
branches:
  - {{name: root, parent: null, length: 1.0, radius: 0.16}}    # root plate + stem below 1 m
  - {{name: lower, parent: root, length: 3.0, radius: 0.15}}
  - {{name: upper, parent: lower, length: 8.0, radius: 0.11}}
grasp: {{branch: upper, fraction: 0.5}}                        # the sling, 8 m up
pull: {{direction: [{_CX:.12f}, 0.0, {_CZ:.12f}]}}
inference:
  joints: [root, lower, upper]
  prior:
    kp: [1.0e4, 1.0e8]        # N m/rad: trees, not twigs
    kd: [1.0e2, 1.0e6]        # N m s/rad
"""


def force_profile(peak, ramp, hold, release, rest=1.0):
    """A pulling test's force: rest, linear ramp, hold, linear release, rest (N at 10 Hz)."""
    knots = np.cumsum([0.0, rest, ramp, hold, release, rest])
    t = np.arange(0.0, knots[-1] + 1e-9, DT)
    return t, np.interp(t, knots, [0.0, 0.0, peak, peak, 0.0, 0.0])


def make_data(tree, seed: int):
    """``{name: (trajectory, channels)}`` from the planar reference, with noise."""
    import treeinfer as ti
    from treeinfer.data.channels import Channel, NamedPoint
    from treeinfer.sim.planar_reference import PlanarTree

    inferred = list(tree.inferred)
    kp = np.array([TRUTH["kp"][n] for n in inferred])
    kd = np.array([TRUTH["kd"][n] for n in inferred])
    a = math.radians(CABLE_DEG)
    d = np.array([math.cos(a), 0.0, -math.sin(a)])
    ref = PlanarTree(tree, kp, kd, direction=d)
    rng = np.random.default_rng(seed)
    quantum = math.radians(NOISE["tilt_quantum_deg"])
    out = {}
    for name, (_, peak, ramp, hold, release) in PULLS.items():
        t, f = force_profile(peak, ramp, hold, release)
        q = ref.rollout_q(f, DT)
        tau = np.array([(ref.grasp_point(qk) - ref.grasp_point(q[0])) @ d for qk in q])
        f_rec = np.round(f / NOISE["force_quantum_N"]) * NOISE["force_quantum_N"]
        x = tau + rng.normal(0.0, NOISE["displacement_m"], tau.shape)
        traj = ti.Trajectory(t, f_rec, x, None, name)
        chans = []
        for sensor, (link, frac) in CLINOS.items():
            tilt = np.array([ref.rotation(qk, q[0], link) for qk in q])[:, [1]]
            rec = np.round((tilt + rng.normal(0.0, NOISE["tilt_rad"], tilt.shape)) / quantum)
            chans.append(Channel(f"{sensor}_{Path(name).stem}", "angle", name,
                                 NamedPoint(link, fraction=frac), ("y",), t, rec * quantum,
                                 sensor=sensor))  # fmt: skip
        out[name] = (traj, tuple(chans))
    return out, kp, kd


def write_inputs(out: Path, tree, data, kp, kd) -> None:
    """OUT/tree.yaml and OUT/data/{train,test}: pulls, channels.yaml, true_params.json."""
    from treeinfer.data.channel_files import write_channels
    from treeinfer.data.trajectories import write_trajectory
    from treeinfer.data.true_params import true_params_record, write_true_params

    for folder in ("train", "test"):
        d = out / "data" / folder
        if d.exists():
            shutil.rmtree(d)
        d.mkdir(parents=True)
        names = [n for n, v in PULLS.items() if v[0] == folder]
        for n in names:
            write_trajectory(d / n, data[n][0])
        write_channels(d, [c for n in names for c in data[n][1]])
        write_true_params(d / "true_params.json",
                          true_params_record(tree, kp, kd, "planar reference"))  # fmt: skip


def dynamic_starts(problem, static_fit) -> np.ndarray:
    """Start points of the dynamic fit from the quasi-static one (a pulling test's natural
    order: the slow pull fixes the stiffness, damping is left to the dynamic model): the
    static posterior's Kp and noise scales (8 of its particles), Kd at 5 values across its box."""
    sp, st = static_fit
    labels = list(problem.labels)
    lo, hi = np.asarray(problem.lower), np.asarray(problem.upper)
    base = 0.5 * (lo + hi)
    out = []
    for row in st[:8]:
        for u in np.linspace(0.2, 0.8, 5):
            x = base.copy()
            for j, lab in enumerate(sp.labels):
                x[labels.index(lab)] = row[j]
            for j, lab in enumerate(labels):
                if lab.startswith("Kd["):
                    x[j] = lo[j] + u * (hi[j] - lo[j])
            out.append(x)
    return np.asarray(out)


def fit(tree, kind: str, train, particles: int, seed: int, log, static_fit=None) -> tuple:
    """``(problem, theta [P, D], record)`` of one model on the training pull."""
    import treeinfer as ti
    from treeinfer.inference.start_pipeline import channel_resample_move, model_importance

    traj, chans = train
    t0 = time.time()
    # the defaults of `treeinfer infer` (static: the load cell's quanta as a force-noise term)
    problem = ti.make_problem(tree, [traj], model_kind=kind, channels=chans)
    extra = None if static_fit is None else dynamic_starts(problem, static_fit)
    imp, idx, lap = model_importance(problem, particles, seed, extra=extra)
    method, theta = "importance", np.asarray(imp.theta, float)
    moved = None
    if not imp.ok:
        moved, theta, _ = channel_resample_move(problem, imp, particles, seed, log)
        theta = np.asarray(theta, float)
        method = "resample-move" + ("" if moved.ok else f" (not settled: {moved.reason})")
    rec = {
        "labels": list(problem.labels),
        "method": method,
        "khat": float(imp.khat),
        "ess": float(imp.ess),
        "seconds": time.time() - t0,
        "simulation": problem.settings.get("sim_step"),
    }
    log(f"{kind}: {method}, k_hat {imp.khat:.2f}, ESS {imp.ess:.0f}, {rec['seconds']:.0f} s")
    return problem, theta, rec


def intervals(problem, theta, kp, kd) -> dict:
    """Per gain column: truth, posterior median and 95% interval (natural units), inside?"""
    layout = problem.model.layout
    truth = layout.theta(kp, kd if layout.infers_damping else None)
    out = {}
    for j, lab in enumerate(problem.labels[: layout.dim]):
        lo, med, hi = np.quantile(theta[:, j], [0.025, 0.5, 0.975])
        out[lab] = {"truth": float(np.exp(truth[j])), "median": float(np.exp(med)),
                    "lower": float(np.exp(lo)), "upper": float(np.exp(hi)),
                    "inside": bool(lo <= truth[j] <= hi)}  # fmt: skip
    return out


def held_out(problem, theta, test) -> tuple[dict, list]:
    """Coverage of the held-out pull by the 95% predictive bands: each inclinometer and the
    displacement; and the channel bands (for the figure)."""
    from treeinfer.evaluation.channel_bands import channel_bands
    from treeinfer.evaluation.predictive import evaluate_trajectories, noise_for

    traj, chans = test
    ok = np.ones(len(theta), bool)
    bands = channel_bands(problem.sim, theta, problem.labels, chans, [traj], problem.settings,
                          ok, model=problem.model)  # fmt: skip
    sigma, kind = noise_for(theta, problem.sim.n_joints, problem.settings)
    m, pred, _ = evaluate_trajectories(problem.sim, theta, list(problem.labels), [traj],
                                       problem.kT, None, None, ok, sigma, kind,
                                       model=problem.model)  # fmt: skip
    res = {b.channel.sensor: b.metrics() for b in bands}
    n = sum(r["samples"] for r in res.values())
    return {
        "channels": res,
        "channels_pct_inside": 100.0
        - sum(r["pct_outside"] * r["samples"] for r in res.values()) / n,
        "displacement_pct_inside": 100.0 - float(m["pct_outside"]),
        "displacement_band_mm": 1e3 * float(m["ci_width"]),
    }, (bands, pred, traj)


def figure(results_bands: dict, path: Path) -> None:
    """Rows: models; columns: the three inclinometers and the displacement on the held-out
    pull, recorded points and the 95% predictive band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = list(results_bands)
    fig, axes = plt.subplots(len(kinds), 4, figsize=(15, 3.1 * len(kinds)), squeeze=False)
    for r, kind in enumerate(kinds):
        bands, pred, traj = results_bands[kind]
        for c, b in enumerate(bands):
            ax = axes[r, c]
            lo, hi = b.band()
            s = 180.0 / math.pi
            ax.fill_between(b.time, s * lo[:, 0], s * hi[:, 0], color="C0", alpha=0.3,
                            label="95% predictive")  # fmt: skip
            ax.plot(b.time, s * b.mean[:, 0], color="C0", lw=1, label="mean")
            ax.plot(b.time, s * b.recorded[:, 0], ".", color="k", ms=2, label="recorded")
            ax.set_title(f"{kind}: {b.channel.sensor} ({b.channel.point.label()})", fontsize=9)
            ax.set_ylabel("tilt [deg]")
        ax = axes[r, 3]
        lo, hi = pred.band()
        ax.fill_between(traj.time, 1e3 * lo[0], 1e3 * hi[0], color="C1", alpha=0.3,
                        label="95% predictive")  # fmt: skip
        ax.plot(traj.time, 1e3 * pred.mean[0], color="C1", lw=1)
        ax.plot(traj.time, 1e3 * traj.displacement, ".", color="k", ms=2, label="recorded")
        ax.set_title(f"{kind}: sling displacement along the cable", fontsize=9)
        ax.set_ylabel("[mm]")
        for ax in axes[r]:
            ax.set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("Held-out pull (3 kN; trained on a 2 kN pull): data from the planar reference")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_cli(out: Path, log) -> dict:
    """The docs' commands: infer with each model, evaluate on the held-out pull."""
    cmds = {}
    for kind in ("static", "dynamic"):
        run, ev = out / f"run_{kind}", out / f"eval_{kind}"
        cmd = [sys.executable, "-m", "treeinfer", "infer", "--tree", str(out / "tree.yaml"),
               "--data", str(out / "data" / "train"), "--model-kind", kind,
               "--out", str(run), "--force"]  # fmt: skip
        t0 = time.time()
        rc = subprocess.run(cmd, cwd=ROOT).returncode
        cmds[f"infer_{kind}"] = {"rc": rc, "seconds": time.time() - t0}
        log(f"infer --model-kind {kind}: exit {rc}, {time.time() - t0:.0f} s")
        if rc not in (0, 4):
            continue
        cmd = [sys.executable, "-m", "treeinfer", "evaluate", "--run", str(run), "--data",
               str(out / "data" / "test"), "--out", str(ev), "--force"]  # fmt: skip
        rc = subprocess.run(cmd, cwd=ROOT).returncode
        cmds[f"evaluate_{kind}"] = {"rc": rc}
        if rc == 0:
            cmds[f"evaluate_{kind}"]["metrics"] = json.loads((ev / "metrics.json").read_text())
    return cmds


def results_md(res: dict) -> str:
    lines = ["# Static pulling test, worked example (experiments/static_pulling_example.py)", "",
             f"seed {res['seed']}, {res['particles']} particles; data from the planar reference "
             "(full dynamics), noise: tilt 0.003 deg + 0.001 deg quanta, force 10 N quanta, "
             "displacement 1 mm.", "",
             "## Truths inside the 95% intervals (trained on the 2 kN pull)", "",
             "| model | parameter | truth | median | 95% interval | inside |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for kind, r in res["models"].items():
        for lab, p in r["intervals"].items():
            lines.append(f"| {kind} | {lab} | {p['truth']:.3g} | {p['median']:.3g} | "
                         f"[{p['lower']:.3g}, {p['upper']:.3g}] | "
                         f"{'yes' if p['inside'] else 'no'} |")  # fmt: skip
    lines += [
        "",
        "## Held-out pull (3 kN): share of recorded points inside the 95% predictive band",
        "",
        "| model | clino_0.5m | clino_2m | clino_6m | all clinos | "
        "displacement | method | k_hat | seconds |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for kind, r in res["models"].items():
        h = r["held_out"]
        c = {k: 100.0 - v["pct_outside"] for k, v in h["channels"].items()}
        lines.append(f"| {kind} | {c['clino_0.5m']:.1f}% | {c['clino_2m']:.1f}% | "
                     f"{c['clino_6m']:.1f}% | {h['channels_pct_inside']:.1f}% | "
                     f"{h['displacement_pct_inside']:.1f}% | {r['fit']['method']} | "
                     f"{r['fit']['khat']:.2f} | {r['fit']['seconds']:.0f} |")  # fmt: skip
    if res.get("cli"):
        lines += ["", "## The CLI commands (docs/pulling_tests.md)", ""]
        for k, v in res["cli"].items():
            lines.append(f"- {k}: exit {v['rc']}")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--particles", type=int, default=128)
    p.add_argument("--models", nargs="+", default=["static", "dynamic"])
    p.add_argument("--cli", action="store_true", help="also run the docs' CLI commands")
    args = p.parse_args(argv)
    import treeinfer as ti

    def log(m):
        print(m, flush=True)

    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    (out / "tree.yaml").write_text(TREE_YAML)
    tree = ti.load_tree(out / "tree.yaml")
    data, kp, kd = make_data(tree, args.seed)
    write_inputs(out, tree, data, kp, kd)
    train = data["pull_2kN.csv"]
    test = data["pull_3kN.csv"]
    res = {"config": CONFIG, "seed": args.seed, "particles": args.particles, "models": {}}
    figs = {}
    static_fit = None
    for kind in args.models:
        problem, theta, rec = fit(tree, kind, train, args.particles, args.seed, log,
                                  static_fit if kind == "dynamic" else None)  # fmt: skip
        if kind == "static":
            static_fit = (problem, theta)
        ho, figs[kind] = held_out(problem, theta, test)
        res["models"][kind] = {"fit": rec, "intervals": intervals(problem, theta, kp, kd),
                               "held_out": ho}  # fmt: skip
        log(json.dumps(res["models"][kind], default=float))
        (out / "results.json").write_text(json.dumps(res, indent=1, default=float))
    figure(figs, out / "heldout_bands.png")
    shutil.copy(out / "heldout_bands.png", ROOT / "docs" / "img" / "static_pulling_example.png")
    if args.cli:
        res["cli"] = run_cli(out, log)
    (out / "results.json").write_text(json.dumps(res, indent=1, default=float))
    (out / "results.md").write_text(results_md(res))
    print(results_md(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
