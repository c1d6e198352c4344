"""Leave-one-height-out on synthetic quasi-static stem pushes (issue 13's Target, stand-in data).

A tapered elastic stem (treeinfer.synthetic_stem, not a hinge chain) is pushed sideways at three
heights; the logger writes raw CSVs (gf, mm, a wrapping ms counter, jitter, a load offset,
noise). For each held-out height:

1. ``import_csv`` the three logs (units, wrap-around, tare, contact zero, trim, sidecar);
2. fit a 3-link vertical hinge chain (stiffness only) with the static model
   (``treeinfer.static.static_rollout``) and a Gaussian likelihood on displacement with an
   unknown noise sigma, to the two other heights;
3. predict the held-out height: the 95% predictive band (parameters + noise) and its mean;
4. compare with the one-parameter cantilever ``x = F h^3 / 3EI`` fitted to the same two heights.

Reported per fold: share of held-out measured points inside the 95% band, RMSE of the
predictive mean and of the cantilever (m). Target: >= 90% inside, RMSE <= cantilever's.

The sampler is an affine-invariant ensemble (Goodman & Weare stretch move): tuning-free in 4
dimensions, and each move evaluates half the walkers in one batched static solve. (emcee is
not installed here; the move is a few lines.) The integrator's ``infer --model-kind static
--likelihood gaussian`` will use the library's samplers instead.

    JAX_PLATFORMS=cpu python experiments/stem_pushes.py [--steps 800] [--walkers 32]
"""

from __future__ import annotations

import argparse
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
from treeinfer.pulls import load_data_pulls, stack_resolved
from treeinfer.sim import make_simulator
from treeinfer.static import static_rollout
from treeinfer.synthetic_stem import (
    Stem,
    branch_at_height,
    cantilever_displacement,
    compliance,
    fit_cantilever,
    stem_tree,
    write_stem_logs,
)
from treeinfer.trajectories import read_trajectory, stack_trajectories

LOG_SIGMA = (np.log(1e-5), np.log(1e-2))  # m


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


def stretch_sampler(logp, x0, steps, rng, a=2.0):
    """Goodman & Weare (2010) stretch move, two halves updated in turn. ``logp``: [W, D] -> [W].
    Returns the chain [steps, W, D] and its log densities [steps, W] (walkers that start where
    the density is zero move to the first finite proposal)."""
    x = np.array(x0, float)
    w, d = x.shape
    lp = logp(x)
    half = w // 2
    chain = np.empty((steps, w, d))
    lps = np.empty((steps, w))
    for s in range(steps):
        for sl, other in ((slice(0, half), slice(half, w)), (slice(half, w), slice(0, half))):
            xs, xo = x[sl], x[other]
            n = xs.shape[0]
            z = ((a - 1.0) * rng.uniform(size=n) + 1.0) ** 2 / a
            partner = xo[rng.integers(0, xo.shape[0], n)]
            prop = partner + z[:, None] * (xs - partner)
            lp_prop = logp(prop)
            with np.errstate(invalid="ignore"):  # -inf - -inf: both outside, reject
                delta = np.where(
                    np.isfinite(lp[sl]),
                    lp_prop - lp[sl],
                    np.where(np.isfinite(lp_prop), np.inf, -np.inf),
                )
            accept = np.log(rng.uniform(size=n)) < (d - 1) * np.log(z) + delta
            xs[accept] = prop[accept]
            lp_s = lp[sl].copy()
            lp_s[accept] = lp_prop[accept]
            x[sl], lp[sl] = xs, lp_s
        chain[s] = x
        lps[s] = lp
    return chain, lps


def fold(sim, tree, trajs, pulls, heights, test: int, args, rng, stem: Stem):
    train = [i for i in range(len(trajs)) if i != test]
    obs = stack_trajectories([trajs[i] for i in train])
    br, fr, di = stack_resolved([pulls[i] for i in train], tree)
    lo, hi = tree.bounds_array()
    r = tree.n_inferred
    box_lo = np.concatenate([np.log(lo[:r]), [LOG_SIGMA[0]]])
    box_hi = np.concatenate([np.log(hi[:r]), [LOG_SIGMA[1]]])
    shape = None
    if args.tied:  # one stiffness scale: Kp_j = s * d_j^4 / l_j (beam-like, from the taper)
        # K_j = E I(z_j) / segment at each hinge's height z_j (segments of equal length)
        from treeinfer.tree import world_frames

        frames = world_frames(tree)
        z = np.array([frames[n][0][2] - tree.base_position[2] for n in tree.inferred])
        ei = np.array([float(stem.ei(h)) for h in z])
        shape = ei / ei.max()
        box_lo = np.array([np.log(lo[0]), LOG_SIGMA[0]])
        box_hi = np.array([np.log(hi[0]) + np.log(1.0 / shape.min()), LOG_SIGMA[1]])
    nk = 1 if args.tied else r

    def gains(theta):
        if shape is None:
            return jnp.exp(theta[:, :r])
        return jnp.exp(theta[:, :1]) * jnp.asarray(shape)[None, :]

    x_obs = jnp.asarray(obs.displacement)
    mask = jnp.asarray(obs.mask, x_obs.dtype)

    @jax.jit
    def loglik(theta):
        roll = static_rollout(
            sim,
            gains(theta),
            obs.force,
            grasp_fraction=fr,
            direction=di,
            grasp_branch=list(br),
            tree=tree,
            iterations=args.newton,
        )
        sigma = jnp.exp(theta[:, nk])[:, None, None]
        res = (roll.tau - x_obs) / sigma
        ll = jnp.sum(mask * (-0.5 * res**2 - jnp.log(sigma)), axis=(1, 2))
        return jnp.where(jnp.all(roll.stable, axis=1), ll, -jnp.inf)

    def logp(theta):
        # every walker is evaluated (clipped into the box) so the batch shape never changes
        # and the static solve compiles once per fold
        inside = np.all((theta > box_lo) & (theta < box_hi), axis=1)
        if (
            args.ordered and not args.tied
        ):  # parent joints at least as stiff as their children (treeinfer's
            # inequality prior, here as a hard constraint); pairs index tree.inferred
            for parent, child in tree.inferred_pairs():
                inside &= theta[:, parent] >= theta[:, child]
        ll = np.asarray(loglik(jnp.asarray(np.clip(theta, box_lo, box_hi))))
        return np.where(inside, ll, -np.inf)

    x0 = rng.uniform(box_lo, box_hi, size=(args.walkers, nk + 1))
    if (
        args.ordered and not args.tied
    ):  # start inside the constraint: a chain is inferred grasp branch first,
        x0[:, :r] = np.sort(x0[:, :r], axis=1)  # so ascending order puts parents above children
    x0[:, nk] = np.log(1e-3) + 0.1 * rng.standard_normal(args.walkers)
    t0 = time.time()
    chain, lps = stretch_sampler(logp, x0, args.steps, rng)
    wall = time.time() - t0
    post = chain[args.steps // 2 :].reshape(-1, nk + 1)
    post = post[np.isfinite(lps[args.steps // 2 :].reshape(-1))]  # walkers still outside: out
    post = post[rng.choice(post.shape[0], min(args.draws, post.shape[0]), replace=False)]

    held = trajs[test]
    pb = pulls[test]
    roll = static_rollout(
        sim,
        gains(jnp.asarray(post)),
        held.force[None],
        grasp_fraction=pb.fraction,
        direction=pb.direction,
        grasp_branch=[pb.branch],
        tree=tree,
        iterations=args.newton,
    )
    tau = np.asarray(roll.tau[:, 0])  # [S, T]
    ok = np.asarray(roll.stable[:, 0])
    tau, sig = tau[ok], np.exp(post[ok, nk])
    draws = tau + sig[:, None] * rng.standard_normal(tau.shape)
    lower, upper = np.percentile(draws, [2.5, 97.5], axis=0)
    mean = tau.mean(axis=0)
    inside = float(np.mean((held.displacement >= lower) & (held.displacement <= upper)))
    rmse = float(np.sqrt(np.mean((mean - held.displacement) ** 2)))
    ei = fit_cantilever(
        [trajs[i].force for i in train],
        [trajs[i].displacement for i in train],
        [heights[i] for i in train],
    )
    cant = cantilever_displacement(held.force, heights[test], ei)
    rmse_c = float(np.sqrt(np.mean((cant - held.displacement) ** 2)))
    return {
        "held_out_height_m": heights[test],
        "inside_95_band": inside,
        "rmse_static_m": rmse,
        "rmse_cantilever_m": rmse_c,
        "cantilever_EI_Nm2": ei,
        "posterior_kp_median": np.median(np.asarray(gains(jnp.asarray(post))), axis=0).tolist(),
        "posterior_sigma_median_m": float(np.exp(np.median(post[:, nk]))),
        "band_width_mean_m": float(np.mean(upper - lower)),
        "sampler_wall_s": wall,
        "n_points": int(held.n_steps),
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
    ap.add_argument("--steps", type=int, default=800)
    ap.add_argument("--walkers", type=int, default=32)
    ap.add_argument("--draws", type=int, default=400)
    ap.add_argument("--newton", type=int, default=12, help="Newton iterations per sample")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--links", type=int, default=3, help="hinged links in the chain (3)")
    ap.add_argument(
        "--hinges",
        choices=("bases", "midpoints"),
        default="bases",
        help="hinge at each segment's base (default) or middle",
    )
    ap.add_argument(
        "--tied",
        action="store_true",
        help="one stiffness scale, Kp_j proportional to d_j^4 / l_j (taper-tied)",
    )
    ap.add_argument(
        "--ordered",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="parent joints at least as stiff as children (default on)",
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
    results = [fold(sim, tree, trajs, pulls, heights, k, args, rng, stem) for k in range(3)]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(
        out / "results.json",
        json.dumps({"folds": results, "stem": stem._asdict(), "args": vars(args)}, indent=2) + "\n",
    )
    lines_note = (
        "one scale, Kp = s EI(z_hinge) / segment (tied)"
        if args.tied
        else "parent >= child stiffness"
        if args.ordered
        else "independent stiffnesses"
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
        f"\n{args.links} links (hinges at segment {args.hinges}), {args.walkers} walkers x "
        f"{args.steps} steps, {lines_note}, seed {args.seed}"
    )
    atomic_write_text(out / "results.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
