"""Observations anywhere (issue 30, section 2): how much does a sensor besides the grasp point
narrow the posterior?

The built-in two-branch tree (``treeinfer/examples/two_branch.yaml``: a parent branch and the
grasped child, both joints inferred) is pulled at the child's grasp point (0.9 of its length);
the data come from an independent simulator (:class:`treeinfer.sim.planar_reference.PlanarTree`:
Lagrange's equations integrated by scipy, no MuJoCo code), with white noise on every channel:

* ``grasp``: the grasp point's displacement (2 mm), as today;
* ``+marker``: plus a camera marker at the middle of the child (x and z, 1 mm, 25 Hz: every
  other sample of the pull's 50 Hz);
* ``+tilt``: plus an inclinometer on the child (rotation about y, 1 mrad, 50 Hz);
* ``+marker+tilt``: both.

The force is recorded clean (``noise_force=None``); every noise scale is inferred (the default).
Each posterior is the start pipeline's generic path for a problem with channels (the MAP and
Laplace covariance of the log-density, then adaptive importance sampling with PSIS weights:
:func:`treeinfer.inference.start_pipeline.model_importance`), run on every sensor set alike so
the comparison does not mix methods (its starts: the grasp-point start pipeline's draws, with
each channel's noise set by a line search: :func:`treeinfer.inference.start_pipeline.
channel_starts`); the std of each parameter is the importance-weighted std
of the log parameter over all draws (``std log K`` ~ the relative std of K).

    python experiments/observations_anywhere.py --seeds 0 1 2   # --out DIR (default below)

Writes ``OUT/results.json`` (config + every number) and ``OUT/results.md`` (the tables).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

CONFIG = {
    "tree": "treeinfer/examples/two_branch.yaml",
    "scenarios": {
        "child": "grasp at 0.9 of the child (the example's grasp point)",
        "parent": "grasp at 0.9 of the parent (a robot that reaches the parent only); both "
        "joints inferred",
    },
    "truth": {"kp": {"child": 40.0, "parent": 80.0}, "kd": {"child": 0.3, "parent": 0.8}},
    "dt": 0.02,
    "duration": 3.0,
    "n_pulls": 2,
    "profiles": "profile_set('mixed', n=2, duration=3.0, dt=0.02, seed=100 + seed)",
    "noise": {"displacement_m": 2e-3, "marker_m": 1e-3, "tilt_rad": 1e-3, "force": "none"},
    "marker": {"link": "child", "fraction": 0.5, "components": "xz", "rate_hz": 25.0},
    "tip_marker": {
        "link": "child",
        "fraction": 1.0,
        "components": "xz",
        "rate_hz": 25.0,
        "noise": "1 mm, drawn from its own stream (rng [seed, 1])",
    },
    "tilt": {"link": "child", "fraction": 0.5, "components": "y", "rate_hz": 50.0},
    "noise_scales": "inferred (sigma_x and one sigma[name] per channel)",
    "posterior": "model_importance(problem, n_particles=256): Laplace at the MAP + adaptive "
    "importance sampling (Student-t, PSIS); weighted std over all draws; resample-move (256 "
    "particles) where the weights are not trusted",
    "likelihood": "gaussian, noise_force=None, nn_prior=True (make_problem's default)",
}
SETS = ("grasp", "+marker", "+tip-marker", "+tilt", "+marker+tilt")
# the single sensors suggest --sensors can score (the linearised prediction of the ratio): a
# 25 Hz marker is scored as a 50 Hz one with sqrt(2) x its noise (the same information)
PREDICT = {
    "+marker": ("position", "child", 0.5, "xz", 1e-3 * 2**0.5),
    "+tip-marker": ("position", "child", 1.0, "xz", 1e-3 * 2**0.5),
    "+tilt": ("angle", "child", 0.5, "y", 1e-3),
}


def make_data(tree, seed: int):
    """Trajectories and channels from the planar reference, with noise."""
    import treeinfer as ti
    from treeinfer.data.channels import Channel, NamedPoint
    from treeinfer.sim.planar_reference import PlanarTree

    dt, c = CONFIG["dt"], CONFIG
    forces = ti.data.forces.profile_set(
        "mixed", n=2, duration=c["duration"], dt=dt, seed=100 + seed
    )
    kp = np.array([c["truth"]["kp"][n] for n in tree.inferred])
    kd = np.array([c["truth"]["kd"][n] for n in tree.inferred])
    ref = PlanarTree(tree, kp, kd)
    rng = np.random.default_rng(seed)
    nz = c["noise"]
    rng_tip = np.random.default_rng([seed, 1])  # the other sets' data stay as they were
    trajs, markers, tilts, tips = [], [], [], []
    for b, f in enumerate(forces):
        q = ref.rollout_q(f, dt)
        t = np.arange(len(f)) * dt
        tau = np.array([(ref.grasp_point(qk) - ref.c_rest) @ ref.direction for qk in q])
        name = f"pull_{b}.csv"
        x = tau + rng.normal(0, nz["displacement_m"], tau.shape)
        trajs.append(ti.Trajectory(t, f, x, None, name))
        m = np.array([ref.point(qk, "child", 0.5) for qk in q])
        m = (m - m[0])[::2][:, [0, 2]]  # 25 Hz camera, x and z
        m = m + rng.normal(0, nz["marker_m"], m.shape)
        point = NamedPoint("child", fraction=0.5)
        markers.append(Channel(f"marker_{b}", "position", name, point, ("x", "z"), t[::2], m))
        a = np.array([ref.rotation(qk, q[0], "child") for qk in q])[:, [1]]
        a = a + rng.normal(0, nz["tilt_rad"], a.shape)
        tilts.append(Channel(f"tilt_{b}", "angle", name, point, ("y",), t, a))
        m = np.array([ref.point(qk, "child", 1.0) for qk in q])
        m = (m - m[0])[::2][:, [0, 2]] + rng_tip.normal(0, nz["marker_m"], (len(t[::2]), 2))
        tip = NamedPoint("child", fraction=1.0)
        tips.append(Channel(f"tip_{b}", "position", name, tip, ("x", "z"), t[::2], m))
    return forces, trajs, {"grasp": (), "+marker": tuple(markers), "+tilt": tuple(tilts),
                           "+marker+tilt": tuple(markers + tilts),
                           "+tip-marker": tuple(tips)}  # fmt: skip


def weighted_std(imp):
    w = np.exp(np.asarray(imp.log_weights, float) - np.max(imp.log_weights))
    w /= w.sum()
    d = np.asarray(imp.draws, float)
    mean = w @ d
    return mean, np.sqrt(w @ (d - mean) ** 2)


def run_seed(tree, seed: int, log) -> dict:
    import treeinfer as ti
    from treeinfer.inference.fast import importance_for_run
    from treeinfer.inference.start_pipeline import (
        channel_resample_move,
        channel_starts,
        model_importance,
    )

    forces, trajs, sets = make_data(tree, seed)
    sim = ti.make_simulator(tree, CONFIG["dt"], forces=forces)
    out = {"sim": {"substeps": sim.substeps, **{k: v for k, v in sim.step_info.items()}}}
    for name in SETS:
        t0 = time.time()
        problem = ti.make_problem(tree, trajs, sim=sim, noise_force=None, channels=sets[name])
        if sets[name]:  # the start pipeline's starts for channels (grasp-point fit + sigma search)
            extra = channel_starts(problem, seed)
        else:  # the same grasp-point fit's draws
            extra = np.asarray(importance_for_run(problem, 16, seed, lambda m: None)[1])
        imp, _, lap = model_importance(problem, 256, seed, extra=extra)
        mean, std = weighted_std(imp)
        method, moved, theta = "importance", None, np.asarray(imp.theta, float)
        if not imp.ok:  # untrusted weights: resample-move, as the start pipeline does
            moved, theta, _ = channel_resample_move(problem, imp, 256, seed, lambda m: None)
            method = "resample-move" + ("" if moved.ok else f" (not settled: {moved.reason})")
            mean, std = theta.mean(0), theta.std(0)
        if name == "grasp":  # what suggest --sensors' linearisation expects of each sensor
            from treeinfer.design.sensors import rank_sensors

            cands = list(PREDICT.values())
            scores = rank_sensors(sim, theta, problem.labels, forces, cands)
            by = {(s_.kind, s_.link, s_.fraction): s_.std_ratio for s_ in scores}
            out["predicted"] = {k: by[(c[0], c[1], c[2])] for k, c in PREDICT.items()}
        r = {
            "labels": list(problem.labels),
            "mean_log": mean.tolist(),
            "std_log": std.tolist(),
            "mean": np.exp(mean).tolist(),
            "khat": float(imp.khat),
            "ess": float(imp.ess),
            "ok": bool(imp.ok),
            "method": method,
            "resample_move": None if moved is None else moved.settings(),
            "seconds": time.time() - t0,
        }
        out[name] = r
        log(
            f"seed {seed} {name:13s} khat {imp.khat:.2f} ess {imp.ess:5.0f} {method} "
            f"{time.time() - t0:5.0f} s  "
            + "  ".join(
                f"{lab} {np.exp(m):.3g} (sd {s:.3f})"
                for lab, m, s in zip(problem.labels, mean, std)
            )  # fmt: skip
        )
    return out


def mh_check(tree, seed: int, sets: list[str], iterations: int, log) -> dict:
    """Random-walk Metropolis chains (64, from the study's own posterior particles, proposal
    from their covariance) as an independent check of the std the study reports."""
    import treeinfer as ti
    from treeinfer.inference.fast import importance_for_run
    from treeinfer.inference.laplace import mh_proposal
    from treeinfer.inference.start_pipeline import (
        channel_resample_move,
        channel_starts,
        model_importance,
    )

    forces, trajs, all_sets = make_data(tree, seed)
    sim = ti.make_simulator(tree, CONFIG["dt"], forces=forces)
    out = {}
    for name in sets:
        t0 = time.time()
        problem = ti.make_problem(tree, trajs, sim=sim, noise_force=None, channels=all_sets[name])
        if all_sets[name]:
            extra = channel_starts(problem, seed)
        else:
            extra = np.asarray(importance_for_run(problem, 16, seed, lambda m: None)[1])
        imp, idx, _ = model_importance(problem, 256, seed, extra=extra)
        theta = np.asarray(imp.theta, float)
        if not imp.ok:
            _, theta, _ = channel_resample_move(problem, imp, 256, seed, lambda m: None)
        start = np.asarray(theta, float)[:: max(1, len(theta) // 64)][:64]
        scale = mh_proposal(np.cov(np.asarray(theta, float), rowvar=False))
        post = ti.infer(
            problem,
            sampler="mh",
            n_particles=len(start),
            n_iterations=iterations,
            seed=seed,
            progress=False,
            initial_theta=start,
            proposal_scale=scale,
        )
        tr = np.asarray(post.run.trace_positions, float)  # [n_trace, P, D]
        draws = tr[tr.shape[0] // 2 :].reshape(-1, tr.shape[-1])
        acc = post.run.diagnostics.get("mean_acceptance_rate")
        out[name] = {
            "labels": list(problem.labels),
            "std_log": draws.std(0).tolist(),
            "mean": np.exp(draws.mean(0)).tolist(),
            "iterations": iterations,
            "chains": len(start),
            "acceptance": None if acc is None else float(np.mean(acc)),
            "seconds": time.time() - t0,
        }
        log(f"MH seed {seed} {name}: " + "  ".join(
            f"{lab} sd {s_:.3f}" for lab, s_ in zip(problem.labels, draws.std(0))))  # fmt: skip
    return out


def mh_table(mh: dict, results_path: Path) -> str:
    """The std of the study against random-walk Metropolis chains on the same data."""
    res = json.loads(results_path.read_text())["seeds"][str(mh["seed"])]
    lines = [
        f"## Check: the study's std against Metropolis chains ({mh['grasp']} grasped, seed "
        f"{mh['seed']})",
        "",
        "64 random-walk Metropolis chains started from the study's particles, proposal from their "
        "covariance, std over the second half of the chains (`--mh-check`; "
        f"`mh_check_{mh['grasp']}.json`). Entries: study / MH.",
        "",
    ]
    sets = list(mh["sets"])
    labels = [lab for lab in mh["sets"][sets[0]]["labels"] if lab.startswith("K")]
    lines.append("| set | " + " | ".join(labels) + " | MH iterations | acceptance |")
    lines.append("| --- | " + " | ".join("---" for _ in labels) + " | --- | --- |")
    for name in sets:
        m, r = mh["sets"][name], res[name]
        cells = [f"{r['std_log'][j]:.3f} / {m['std_log'][j]:.3f}" for j in range(len(labels))]
        acc = "" if m["acceptance"] is None else f"{m['acceptance']:.2f}"
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {m['iterations']} | {acc} |")
    return "\n".join(lines) + "\n"


def tables(results: dict, labels: list[str], grasp: str = "child") -> str:
    seeds = sorted(results["seeds"], key=int)
    truth = CONFIG["truth"]
    lines = [
        f"# Observations anywhere, {grasp} grasped: posterior std with and without a sensor "
        "besides the grasp point",
        "",
        f"Two-branch tree ({grasp} grasped at 0.9, both joints inferred), data from the "
        "independent planar reference "
        "(scipy), 2 pulls x 3 s at 50 Hz; noise 2 mm on the grasp point, 1 mm on the markers "
        "(`+marker`: child middle, `+tip-marker`: child tip; x and z, 25 Hz), 1 mrad on the tilt "
        "(child, about y, 50 Hz); clean force; every noise scale inferred. Posterior: Laplace + "
        "adaptive importance sampling, weighted std of log K over all draws; resample-move "
        "(Metropolis sweeps from the resampled draws, std of its 256 particles) where the weights "
        "fail their check (column `posterior`). Config and every number: "
        f"`results_{grasp}.json`.",
        "",
        "## Ratio std(grasp alone) / std(grasp + sensor), geometric mean over seeds "
        f"{', '.join(seeds)} (per seed in brackets)",
        "",
        "| parameter | truth | " + " | ".join(s for s in SETS[1:]) + " |",
        "| --- | --- | " + " | ".join("---" for _ in SETS[1:]) + " |",
    ]
    for j, lab in enumerate(labels):
        kind, joint = lab.split("[")[0], lab.split("[")[1].rstrip("]")
        cells = []
        for s in SETS[1:]:
            r = [results["seeds"][k]["grasp"]["std_log"][j] / results["seeds"][k][s]["std_log"][j]
                 for k in seeds]  # fmt: skip
            g = float(np.exp(np.mean(np.log(r))))
            cells.append(f"**{g:.2f}x** [{', '.join(f'{x:.2f}' for x in r)}]")
        lines.append(f"| {lab} | {truth[kind.lower()][joint]:g} | " + " | ".join(cells) + " |")
    pred = [k for k in seeds if "predicted" in results["seeds"][k]]
    if pred:
        sets = [s for s in SETS[1:] if s in PREDICT]
        lines += [
            "",
            "## The same ratios as `suggest --sensors` predicts them (linearised at the "
            "grasp-only posterior mean; geometric mean over seeds)",
            "",
            "| parameter | " + " | ".join(sets) + " |",
            "| --- | " + " | ".join("---" for _ in sets) + " |",
        ]
        for lab in labels:
            cells = []
            for s in sets:
                r = [results["seeds"][k]["predicted"][s][lab] for k in pred]
                cells.append(f"{float(np.exp(np.mean(np.log(r)))):.2f}x")
            lines.append(f"| {lab} | " + " | ".join(cells) + " |")
    lines += ["", "## Posterior mean and std of log K per seed", ""]
    lines.append("| seed | set | " + " | ".join(labels) + " | k-hat | ESS | posterior | s |")
    lines.append(
        "| --- | --- | " + " | ".join("---" for _ in labels) + " | --- | --- | --- | --- |"
    )
    for k in seeds:
        for s in SETS:
            r = results["seeds"][k][s]
            cells = [f"{r['mean'][j]:.3g} (sd {r['std_log'][j]:.3f})" for j in range(len(labels))]
            lines.append(
                f"| {k} | {s} | " + " | ".join(cells)
                + f" | {r['khat']:.2f} | {r['ess']:.0f} | {r.get('method', 'importance')} | "
                f"{r['seconds']:.0f} |"
            )  # fmt: skip
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--grasp", choices=("child", "parent"), default="child")
    ap.add_argument(
        "--mh-check",
        nargs="*",
        default=None,
        metavar="SET",
        help="instead of the study: Metropolis chains on these sets of --seeds[0] (default "
        "grasp +marker), written to mh_check_<grasp>.json",
    )
    ap.add_argument("--mh-iterations", type=int, default=1500)
    ap.add_argument(
        "--tables-only", action="store_true", help="rewrite results.md from the results_*.json"
    )
    ap.add_argument("--out", type=Path, default=ROOT / "experiments/results/observations_anywhere")
    args = ap.parse_args(argv)
    import treeinfer as ti
    from treeinfer.io.provenance import versions

    tree = ti.load_tree(ROOT / CONFIG["tree"])
    if args.grasp == "parent":
        tree = tree.with_grasp(0.9, "parent")  # tree.inferred stays (child, parent)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.mh_check is not None:
        sets = args.mh_check or ["grasp", "+marker"]
        res = mh_check(
            tree, args.seeds[0], sets, args.mh_iterations, lambda m: print(m, flush=True)
        )
        record = {"seed": args.seeds[0], "grasp": args.grasp, "sets": res}
        (args.out / f"mh_check_{args.grasp}.json").write_text(json.dumps(record, indent=1))
        return 0
    config = {**CONFIG, "grasp": args.grasp, "seeds": args.seeds, "versions": versions()}
    results = {"config": config, "seeds": {}}
    path = args.out / f"results_{args.grasp}.json"
    for seed in [] if args.tables_only else args.seeds:
        results["seeds"][str(seed)] = run_seed(tree, seed, lambda m: print(m, flush=True))
        path.write_text(json.dumps(results, indent=1))
    md = []
    for grasp in ("child", "parent"):
        p = args.out / f"results_{grasp}.json"
        if p.exists():
            res = json.loads(p.read_text())
            first = res["seeds"][sorted(res["seeds"], key=int)[0]]
            labels = [lab for lab in first["grasp"]["labels"] if "[" in lab]
            md.append(tables(res, labels, grasp))
    for grasp in ("child", "parent"):
        p = args.out / f"mh_check_{grasp}.json"
        if p.exists() and (args.out / f"results_{grasp}.json").exists():
            md.append(mh_table(json.loads(p.read_text()), args.out / f"results_{grasp}.json"))
    (args.out / "results.md").write_text("\n".join(md))
    print((args.out / "results.md").read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
