"""Leave-one-height-out on synthetic quasi-static stem pushes (issue 13's Target, stand-in data).

A tapered elastic stem (treeinfer.synthetic_stem, not a hinge chain) is pushed sideways at three
heights; the logger writes raw CSVs (gf, mm, a wrapping ms counter, jitter, a load offset,
noise). For each held-out height:

1. ``import_csv`` the three logs (units, wrap-around, tare, contact zero, trim, sidecar);
2. fit a vertical hinge chain with the static model and a Gaussian likelihood with sigma_x
   inferred (``make_problem(model_kind static, likelihood gaussian)``, the library path of
   ``infer --model-kind static --likelihood gaussian``) to the two other heights, sampled by
   the library's Metropolis-Hastings (``infer(problem, "mh")``). The default model is 8 hinges
   at segment midpoints with their stiffnesses tied along the taper (one free scale,
   :func:`treeinfer.static.tied_layout`); ``--no-tied --links 3`` fits free stiffnesses;
3. predict the held-out height (``evaluate_trajectories`` at its own pull): the 95% predictive
   band (parameters + noise) and its mean;
4. compare with the one-parameter cantilever ``x = F h^3 / 3EI`` fitted to the same two heights.

Reported per fold: share of held-out measured points inside the 95% band, RMSE of the
predictive mean and of the cantilever (m). Target: >= 90% inside, RMSE <= cantilever's.

    JAX_PLATFORMS=cpu python experiments/stem_pushes.py [--steps 1500] [--walkers 64]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

if __name__ == "__main__":  # run as a script from anywhere: use this checkout's treeinfer
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import jax
import jax.numpy as jnp
import numpy as np

from treeinfer._io import atomic_write_text
from treeinfer.csv_import import import_csv
from treeinfer.evaluation import evaluate_trajectories
from treeinfer.inference import infer, make_problem
from treeinfer.pulls import load_data_pulls, stack_resolved
from treeinfer.sim import make_simulator
from treeinfer.static import model_for, tied_layout
from treeinfer.synthetic_stem import (
    Stem,
    branch_at_height,
    cantilever_displacement,
    compliance,
    fit_cantilever,
    stem_tree,
    write_stem_logs,
)
from treeinfer.trajectories import read_trajectory


def import_logs(folder: Path, stem: Stem, tree, seed: int):
    raw = write_stem_logs(folder / "raw", stem, seed=seed)
    for path, push in raw:
        branch, distance = branch_at_height(tree, push.height)
        import_csv(
            [path],
            folder / "data",
            time="millis",
            force="load_g",
            displacement="pos_mm",
            units="time=ms,force=gf,displacement=mm",
            dt=0.5,
            tare=True,
            zero_displacement="contact",
            trim=True,
            grasp_branch=branch,
            grasp_distance=distance,
            direction="horizontal",
            tree=tree,
        )
    names = [p.stem + ".csv" for p, _ in raw]
    trajs = [read_trajectory(folder / "data" / n) for n in names]
    pulls = load_data_pulls(folder / "data", tree, names)
    return trajs, pulls, [push.height for _, push in raw]


def taper_shape(tree, stem: Stem) -> np.ndarray:
    """[R] relative hinge stiffnesses ``E I(z_j) / l`` at each hinge's height (segments of
    equal length), normalised to the stiffest: the taper tie of :func:`tied_layout`."""
    from treeinfer.tree import world_frames

    frames = world_frames(tree)
    z = np.array([frames[n][0][2] - tree.base_position[2] for n in tree.inferred])
    ei = np.array([float(stem.ei(h)) for h in z])
    return ei / ei.max()


def _warm_start(problem, n: int, rng) -> np.ndarray:
    """[n, D] chains started around the best point of a coarse grid over the stiffness scale
    (noise at its data estimate), spread by 0.05 in every log column: MH's random walk then
    spends its steps in the posterior instead of crossing a 7-decade box."""
    d = problem.dim
    grid = np.linspace(problem.lower[0], problem.upper[0], 64)
    theta = np.tile(0.5 * (problem.lower + problem.upper), (64, 1))
    theta[:, 0] = grid
    logp = np.asarray(problem.log_density(jnp.asarray(theta)))
    best = theta[int(np.nanargmax(np.where(np.isfinite(logp), logp, -np.inf)))]
    return best + 0.05 * rng.standard_normal((n, d))


def fold(sim, tree, trajs, pulls, heights, test: int, args, rng, stem: Stem):
    """Infer on the two other heights, predict the held-out one: library calls only
    (``make_problem(model_kind static, likelihood gaussian)`` -> ``infer`` -> the held-out
    metrics of ``evaluate``)."""
    train = [i for i in range(len(trajs)) if i != test]
    br, fr, di = stack_resolved([pulls[i] for i in train], tree)
    model = model_for(tree, "static")
    if args.tied:  # one stiffness scale, Kp_j = s * E I(z_j) / l (beam-like, from the taper)
        lo, hi = tree.bounds_array()
        shape = taper_shape(tree, stem)
        model = model._replace(
            layout=tied_layout(tree, shape, (lo[0], hi[0] / shape.min()), model.layout.fixed_kd)
        )
    model = model._replace(direction=di, grasp_branch=tuple(br))
    problem = make_problem(
        tree,
        [trajs[i] for i in train],
        nn_prior=False,
        sim=sim,
        likelihood="gaussian",
        grasp_fraction=fr,
        model=model,
    )
    problem = dataclasses.replace(problem, log_density=jax.jit(problem.log_density))
    t0 = time.time()
    start = _warm_start(problem, args.walkers, rng) if args.tied else None
    post = infer(
        problem,
        "mh",
        n_particles=args.walkers,
        n_iterations=args.steps,
        seed=args.seed + test,
        progress=False,
        initial_theta=start,
        proposal_scale=args.proposal,
    )
    wall = time.time() - t0
    held = trajs[test]
    pb = pulls[test]
    held_model = model._replace(direction=pb.direction[None], grasp_branch=(pb.branch,))
    sigma = np.exp(post.theta[:, -1])  # the inferred noise column, m
    m, pred, _ = evaluate_trajectories(
        sim,
        post.theta,
        list(problem.labels),
        [held],
        problem.kT,
        np.array([pb.fraction]),
        particle_ok=post.valid,
        noise_sigma=sigma,
        noise_kind="gaussian",
        model=held_model,
    )
    mean = pred.mean[0]
    rmse = float(np.sqrt(np.mean((mean - held.displacement) ** 2)))
    ei = fit_cantilever(
        [trajs[i].force for i in train],
        [trajs[i].displacement for i in train],
        [heights[i] for i in train],
    )
    cant = cantilever_displacement(held.force, heights[test], ei)
    rmse_c = float(np.sqrt(np.mean((cant - held.displacement) ** 2)))
    kp, _ = model.layout.gains(jnp.asarray(post.theta[post.valid]))
    lo_b, hi_b = pred.band()
    return {
        "held_out_height_m": heights[test],
        "inside_95_band": 1.0 - m["pct_outside"] / 100.0,
        "rmse_static_m": rmse,
        "rmse_cantilever_m": rmse_c,
        "cantilever_EI_Nm2": ei,
        "posterior_kp_median": np.median(np.asarray(kp), axis=0).tolist(),
        "posterior_sigma_median_m": float(np.median(sigma)),
        "band_width_mean_m": float(np.mean(hi_b[0] - lo_b[0])),
        "sampler_wall_s": wall,
        "n_points": int(held.n_steps),
        "valid_chains": int(post.valid.sum()),
    }


def analytic_table(stem: Stem, heights=(0.12, 0.24, 0.36)) -> list[str]:
    """Model error alone (no noise, no sampling): leave-one-height-out relative error of the
    held-out compliance for one-scale models fitted to the other two heights' true compliances.
    Hinge chains use the small-deflection compliance ``sum_j (h - z_j)^2 / K_j`` over hinges
    below h, with ``K_j = E I(z) / l`` (taper-tied); "midpoints" puts each hinge at its
    segment's middle (a beam segment replaced by a hinge there is exact to second order)."""
    hs = np.asarray(heights)
    c_true = np.array([compliance(stem, h) for h in hs])

    def chain(joints, stiff):
        return lambda h: sum((h - z) ** 2 / k for z, k in zip(joints, stiff) if z < h)

    def loo(model):
        g = np.array([model(h) for h in hs])
        errs = []
        for k in range(len(hs)):
            tr = [i for i in range(len(hs)) if i != k]
            scale = np.sum(g[tr] * c_true[tr]) / np.sum(g[tr] ** 2)  # least squares c ~ scale g
            errs.append(scale * g[k] / c_true[k] - 1.0)
        return errs

    rows = [("uniform cantilever (1 parameter)", loo(lambda h: h**3 / 3.0))]
    for n, where in ((3, "bases"), (3, "midpoints"), (8, "midpoints")):
        step = stem.height / n
        joints = [(i + (0.5 if where == "midpoints" else 0.0)) * step for i in range(n)]
        mids = [z + (0.0 if where == "midpoints" else step / 2) for z in joints]
        rows.append(
            (
                f"{n} hinges at segment {where}, taper-tied (1 parameter)",
                loo(chain(joints, [float(stem.ei(m)) / step for m in mids])),
            )
        )
    head = "| model | " + " | ".join(f"held out {h:.2f} m" for h in hs) + " |"
    out = [head, "|---" * (len(hs) + 1) + "|"]
    out += [
        f"| {name} | " + " | ".join(f"{100 * e:+.1f}%" for e in errs) + " |" for name, errs in rows
    ]
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=1500, help="MH iterations per chain")
    ap.add_argument("--walkers", type=int, default=64, help="MH chains (final states = draws)")
    ap.add_argument(
        "--proposal", type=float, default=0.003, help="MH step, share of each box width"
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--links", type=int, default=8, help="hinged links in the chain (8)")
    ap.add_argument(
        "--hinges",
        choices=("bases", "midpoints"),
        default="midpoints",
        help="hinge at each segment's base or middle (default)",
    )
    ap.add_argument(
        "--tied",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="one stiffness scale, Kp_j proportional to E I(z_j) / l (taper-tied; default on)",
    )
    ap.add_argument("--out", default="experiments/results/stem_pushes")
    ap.add_argument(
        "--analytic", action="store_true", help="print the model-error table (no sampling) and exit"
    )
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    stem = Stem()
    if args.analytic:
        print("\n".join(analytic_table(stem)))
        return
    tree = stem_tree(stem, n_links=args.links, kp_bounds=(0.05, 50.0), hinges=args.hinges)
    sim = make_simulator(tree, obs_dt=0.5, backend="fused")
    with tempfile.TemporaryDirectory() as tmp:
        trajs, pulls, heights = import_logs(Path(tmp), stem, tree, args.seed)
    results = []
    for k in range(3):
        results.append(fold(sim, tree, trajs, pulls, heights, k, args, rng, stem))
        r = results[-1]
        print(
            f"held out {r['held_out_height_m']:.2f} m: {r['inside_95_band']:.0%} inside, "
            f"RMSE {1e3 * r['rmse_static_m']:.3f} mm (cantilever "
            f"{1e3 * r['rmse_cantilever_m']:.3f} mm), {r['sampler_wall_s']:.0f} s",
            flush=True,
        )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(
        out / "results.json",
        json.dumps({"folds": results, "stem": stem._asdict(), "args": vars(args)}, indent=2) + "\n",
    )
    lines_note = (
        "one scale, Kp = s EI(z_hinge) / segment (tied)" if args.tied else "free stiffnesses"
    )
    lines = [
        "| held-out height (m) | inside 95% band | RMSE static (mm) | RMSE cantilever (mm) |",
        "|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| {r['held_out_height_m']:.2f} | {r['inside_95_band']:.0%} | "
            f"{1e3 * r['rmse_static_m']:.3f} | {1e3 * r['rmse_cantilever_m']:.3f} |"
        )
    lines.append(
        f"\n{args.links} links (hinges at segment {args.hinges}), MH {args.walkers} chains x "
        f"{args.steps} steps (proposal {args.proposal} box widths), {lines_note}, static model, "
        f"Gaussian noise with sigma_x inferred, seed {args.seed}"
    )
    atomic_write_text(out / "results.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
