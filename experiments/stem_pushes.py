"""Leave-one-height-out on synthetic quasi-static stem pushes (issue 13's Target, stand-in data).

A tapered elastic stem (treeinfer.tree.stem, not a hinge chain) is pushed sideways at three
heights; the logger writes raw CSVs (gf, mm, a wrapping ms counter, jitter, a load offset,
noise). For each held-out height:

1. ``import_csv`` the three logs (units, wrap-around, tare, contact zero, trim, sidecar);
2. fit a vertical hinge chain with the static model and a Gaussian likelihood with sigma_x
   inferred (``make_problem(model_kind static, likelihood gaussian)``, the library path of
   ``infer --model-kind static --likelihood gaussian``) to the two other heights, sampled by
   the library's Metropolis-Hastings (``infer(problem, "mh")``). The default model is 8 hinges
   at segment midpoints with their stiffnesses tied along the taper (one free scale,
   :func:`treeinfer.inference.tied_layout`); ``--no-tied --links 3`` fits free stiffnesses;
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

from treeinfer.data import load_data_pulls, read_trajectory, stack_resolved
from treeinfer.data.import_csv import import_csv
from treeinfer.evaluation import evaluate_trajectories, force_noise_for
from treeinfer.inference import force_noise_estimate, infer, make_problem, model_for
from treeinfer.io.atomic import atomic_write_text
from treeinfer.sim import make_simulator
from treeinfer.tree.description import world_frames
from treeinfer.tree.stem import (
    G0,
    Stem,
    branch_at_height,
    cantilever_displacement,
    compliance,
    fit_cantilever,
    matched_hinges,
    stem_tree,
    write_stem_logs,
)


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


def _laplace(problem, args, seed: int):
    """The fold's Laplace approximation: ``--laplace exact`` (default):
    :func:`treeinfer.inference.exact_laplace` (the MAP by Newton's method on the exact gradient of
    the static model, the covariance from its differences); ``values``: the generic
    :func:`treeinfer.inference.problem_laplace` (Hessian from differences of values: on this
    problem its MAP stops short and its covariance is 7x too wide in log sigma_x, the cause of
    the earlier R-hat 2-5)."""
    from treeinfer.inference import exact_laplace, problem_laplace

    if args.laplace == "exact":
        return exact_laplace(problem, seed=seed)
    return problem_laplace(problem, seed=seed)


def _mh_draws(problem, args, seed: int):
    """Posterior draws by the library's MH (``infer(problem, "mh")``), started and tuned from
    the problem's Laplace approximation (:func:`_laplace`), then adapted once:

    1. warm-up: ``args.walkers`` chains from Laplace draws, proposal ``2.38/sqrt(D)`` times
       the Laplace covariance's Cholesky factor, ``args.warmup`` steps;
    2. the proposal re-estimated from the pooled second half of the warm-up (the posterior's
       own covariance, not the Laplace one) of the chains within 10 nats of the best one (the
       others restart from their end states), ``args.steps`` steps from the warm-up's ends.

    Returns (draws [N, D] of every chain over all of step 2 (after the warm-up), thinned to at
    most ``args.draws``; split R-hat per column over all chains of step 2 (arviz); acceptance;
    seconds)."""
    from treeinfer.inference import mh_proposal, problem_laplace_particles
    from treeinfer.inference.diagnostics import arviz_compat as az

    t0 = time.time()
    lap = _laplace(problem, args, seed)
    print(f"  Laplace: {time.time() - t0:.0f} s, log-density {lap.log_density:.1f}", flush=True)
    start = problem_laplace_particles(jax.random.key(seed), lap, args.walkers)
    warm = infer(
        problem,
        "mh",
        n_particles=args.walkers,
        n_iterations=args.warmup,
        seed=seed,
        progress=False,
        initial_theta=start,
        proposal_scale=mh_proposal(lap.cov),
    )
    half = warm.run.trace_positions.shape[0] // 2
    tr = warm.run.trace_positions[half:]  # [T, P, D]
    # chains stuck far below the others (a mean log-density more than 10 nats under the best
    # chain's) would inflate the pooled covariance and freeze every chain's proposal: they are
    # left out of it and restarted from the end states of the others
    mean_ld = np.nanmean(
        np.where(
            np.isfinite(warm.run.trace_logdensity[half:]), warm.run.trace_logdensity[half:], np.nan
        ),
        axis=0,
    )
    good = np.isfinite(mean_ld) & (mean_ld >= np.nanmax(mean_ld) - 10.0)
    cov = np.cov(tr[:, good].reshape(-1, tr.shape[-1]).T)
    ends = np.asarray(warm.theta)[good]
    pick = np.random.default_rng(seed).integers(0, len(ends), args.walkers)
    start = np.where(good[:, None], np.asarray(warm.theta), ends[pick])
    post = infer(
        problem,
        "mh",
        n_particles=args.walkers,
        n_iterations=args.steps,
        seed=seed + 1000,
        progress=False,
        initial_theta=jnp.asarray(start),
        proposal_scale=mh_proposal(cov),
    )
    run = post.run
    keep = run.trace_positions[1:]  # [T, P, D]: every chain, every step after the warm-up
    rhat = az.rhat(np.swapaxes(keep, 0, 1))["x"].values
    acc = float(np.mean(run.diagnostics["mean_acceptance_rate"]))
    draws = keep.reshape(-1, keep.shape[-1])
    stride = max(1, len(draws) // args.draws)
    print(f"  warm-up: {int(good.sum())}/{len(good)} chains kept, acceptance {acc:.2f}", flush=True)
    return draws[::stride], np.asarray(rhat, float), acc, time.time() - t0


def _nuts_draws(problem, args, seed: int):
    """Posterior draws by BlackJAX NUTS on the problem's own log-density (the static model's
    settle is differentiable: ``lax.custom_root`` gives its implicit derivatives), started from
    the problem's Laplace approximation (:func:`treeinfer.inference.problem_laplace`):

    ``args.walkers`` chains from Laplace draws, each with its own Stan-style window adaptation
    (``blackjax.window_adaptation``: step size to 0.8 acceptance, dense inverse mass matrix
    started at the Laplace covariance) over ``args.warmup`` steps, then ``args.steps`` NUTS
    steps; chains run one after the other (``lax.map``: on CPU a vmapped batch of chains cost
    more per chain than one chain, measured 0.23 s against 0.13 s per gradient).

    Returns (draws [N, D] over all chains, thinned to at most ``args.draws``; split R-hat per
    column over the chains (arviz); mean acceptance; seconds; divergences (count))."""
    import blackjax

    from treeinfer.inference import problem_laplace_particles
    from treeinfer.inference.diagnostics import arviz_compat as az

    t0 = time.time()
    lap = _laplace(problem, args, seed)
    start = jnp.asarray(problem_laplace_particles(jax.random.key(seed), lap, args.walkers))

    def logdensity(x):  # [D] -> scalar; the problem's density takes a batch [N, D]
        return problem.log_density(x[None])[0]

    inv_mass = jnp.asarray(lap.cov)
    warm = blackjax.window_adaptation(
        blackjax.nuts,
        logdensity,
        is_mass_matrix_diagonal=False,
        initial_inverse_mass_matrix=inv_mass,
        initial_step_size=0.5,
        max_num_doublings=args.max_doublings,
    )
    k_warm, k_run = jax.random.split(jax.random.key(seed + 1000))

    @jax.jit
    def adapt(keys, x0):
        def one(key, x):
            (state, params), _ = warm.run(key, x, num_steps=args.warmup)
            return state, params

        return jax.lax.map(lambda a: one(*a), (keys, x0))

    states, params = adapt(jax.random.split(k_warm, args.walkers), start)

    @jax.jit
    def sample(keys, states, params):
        def one(key, state, p):
            p = {k: v for k, v in p.items() if k != "max_num_doublings"}  # a static int here
            kernel = blackjax.nuts(logdensity, **p, max_num_doublings=args.max_doublings).step

            def body(s, k):
                s, info = kernel(k, s)
                return s, (s.position, info.acceptance_rate, info.is_divergent)

            _, out = jax.lax.scan(body, state, jax.random.split(key, args.steps))
            return out

        return jax.lax.map(lambda a: one(*a), (keys, states, params))

    pos, acc, div = sample(jax.random.split(k_run, args.walkers), states, params)
    pos = np.asarray(pos)  # [P, T, D]
    rhat = az.rhat(pos)["x"].values
    draws = pos.reshape(-1, pos.shape[-1])
    stride = max(1, len(draws) // args.draws)
    n_div = int(np.sum(np.asarray(div)))
    print(
        f"  NUTS: acceptance {float(np.mean(acc)):.2f}, {n_div} divergences, step sizes "
        f"{np.round(np.asarray(params['step_size']), 3).tolist()}",
        flush=True,
    )
    return draws[::stride], np.asarray(rhat, float), float(np.mean(acc)), time.time() - t0, n_div


def matched_layout(tree, heights, args):
    """``--hinges matched``: one hinge per push height (:func:`matched_hinges`), stiffnesses
    tied to the shape that makes the chain's compliance the tapered beam's at every push height
    (from the push heights and the diameters alone, no recording), one free scale (soft tie
    ``--tie-scale`` about it, or hard with 0)."""
    from treeinfer.inference import tied_layout

    z, shape = matched_hinges(Stem(), heights)
    frames = world_frames(tree)
    base = float(tree.base_position[2])
    at = {round(float(frames[n][0][2]) - base, 9): n for n in tree.inferred}
    by_name = {at[round(float(v), 9)]: k for v, k in zip(z, shape)}
    shape_inferred = np.array([by_name[n] for n in tree.inferred])
    lo, hi = tree.bounds_array()
    r = len(tree.inferred)
    bounds = (float(np.min(lo[:r] / shape_inferred)), float(np.max(hi[:r] / shape_inferred)))
    tau = args.tie_scale if args.tie_scale > 0 else None
    return tied_layout(tree, shape_inferred, bounds, tau=tau)


def fold(sim, tree, trajs, pulls, heights, test: int, args):
    """Infer on the two other heights, predict the held-out one: library calls only
    (``make_problem(model_kind static, likelihood gaussian)`` with the tree's own tie ->
    ``infer(problem, "mh")`` -> the held-out metrics of ``evaluate``)."""
    train = [i for i in range(len(trajs)) if i != test]
    br, fr, di = stack_resolved([pulls[i] for i in train], tree)
    model = model_for(tree, "static")._replace(direction=di, grasp_branch=tuple(br))
    if args.hinges == "matched":  # the tie's shape: the chain matching the beam at each height
        model = model._replace(layout=matched_layout(tree, heights, args))
    # the load cell's noise, from the training recordings' force signals alone
    f_noise = force_noise_estimate([trajs[i] for i in train]) if args.force_noise else None
    problem = make_problem(
        tree,
        [trajs[i] for i in train],
        nn_prior=False,
        sim=sim,
        likelihood="gaussian",
        grasp_fraction=fr,
        model=model,
        noise_force=f_noise,
        gradient="autodiff",  # exact: the equilibrium's implicit derivatives
    )
    problem = dataclasses.replace(problem, log_density=jax.jit(problem.log_density))
    n_div = None
    seed = (args.seed if args.sampler_seed is None else args.sampler_seed) + test
    if args.sampler == "nuts":
        theta, rhat, acc, wall, n_div = _nuts_draws(problem, args, seed)
    else:
        theta, rhat, acc, wall = _mh_draws(problem, args, seed)
    held = trajs[test]
    pb = pulls[test]
    held_model = model._replace(direction=pb.direction[None], grasp_branch=(pb.branch,))
    sigma = np.exp(theta[:, -1])  # the inferred noise column, m
    m, pred, _ = evaluate_trajectories(
        sim,
        theta,
        list(problem.labels),
        [held],
        problem.kT,
        np.array([pb.fraction]),
        noise_sigma=sigma,
        noise_kind="gaussian",
        model=held_model,
        # the load-cell term of the band: each draw's compliance at the held-out pull, as
        # `evaluate` does for a static run with --noise-force
        force_noise=force_noise_for(problem.settings),
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
    kp, _ = model.layout.gains(jnp.asarray(theta))
    lo_b, hi_b = pred.band()
    return {
        "held_out_height_m": heights[test],
        "inside_95_band": 1.0 - m["pct_outside"] / 100.0,
        "rmse_static_m": rmse,
        "rmse_cantilever_m": rmse_c,
        "cantilever_EI_Nm2": ei,
        "posterior_kp_median": np.median(np.asarray(kp), axis=0).tolist(),
        "posterior_sigma_median_m": float(np.median(np.exp(theta[:, -1]))),
        "held_out_noise_median_m": float(
            np.median(
                np.sqrt(
                    sigma**2
                    + (0.0 if pred.force_variance is None else pred.force_variance[:, 0, 0])
                )
            )
        ),
        "band_includes_force_noise": m.get("band_includes_force_noise", False),
        "laplace": args.laplace,
        "force_noise_N": f_noise,
        "band_width_mean_m": float(np.mean(hi_b[0] - lo_b[0])),
        "rhat_max": float(np.max(rhat)),
        "rhat": dict(zip(problem.labels, np.asarray(rhat, float).tolist())),
        "sampler": args.sampler,
        "acceptance": acc,
        "nuts_divergences": n_div,
        "sampler_wall_s": wall,
        "n_draws": int(len(theta)),
        "n_points": int(held.n_steps),
        "curve": {
            "force_N": held.force.tolist(),
            "recorded_m": held.displacement.tolist(),
            "mean_m": mean.tolist(),
            "lower_m": lo_b[0].tolist(),
            "upper_m": hi_b[0].tolist(),
            "cantilever_m": cant.tolist(),
        },
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
    z, shape = matched_hinges(stem, hs)
    rows.append(
        (
            f"{len(z)} matched hinges (PRB pivots), beam-matched shape (1 parameter)",
            loo(chain(z, shape)),
        )
    )
    from treeinfer.inference import taper_shape

    for n in (3, 8, 16):  # the tree file's tie: Hencky lumping of the branches' radii
        tree = stem_tree(stem, n_links=n, hinges="midpoints", tie="taper")
        frames = world_frames(tree)
        z = [float(frames[j][0][2] - tree.base_position[2]) for j in tree.inferred]
        rows.append(
            (
                f"{n} midpoint hinges, tie: taper from the tree (1 parameter)",
                loo(chain(z, list(taper_shape(tree)))),
            )
        )
    head = "| model | " + " | ".join(f"held out {h:.2f} m" for h in hs) + " |"
    out = [head, "|---" * (len(hs) + 1) + "|"]
    out += [
        f"| {name} | " + " | ".join(f"{100 * e:+.1f}%" for e in errs) + " |" for name, errs in rows
    ]
    return out


def plot_folds(results, path: Path) -> None:
    """Held-out force-displacement per fold: recorded points, the 95% predictive band and mean
    of the hinge chain, and the cantilever fitted to the two other heights."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(4.2 * len(results), 3.6))
    for ax, r in zip(np.atleast_1d(axes), results):
        c = r["curve"]
        f = 1e3 * np.asarray(c["force_N"]) / G0  # gf
        order = np.argsort(f, kind="stable")
        mm = lambda k: 1e3 * np.asarray(c[k])[order]  # noqa: E731
        ax.fill_between(
            f[order],
            mm("lower_m"),
            mm("upper_m"),
            color="C0",
            alpha=0.3,
            label="95% predictive band",
            lw=0,
        )
        ax.plot(f[order], mm("mean_m"), "C0-", lw=1, label="predictive mean")
        ax.plot(f[order], mm("cantilever_m"), "C3--", lw=1, label="cantilever (2 heights)")
        ax.plot(f, 1e3 * np.asarray(c["recorded_m"]), "k.", ms=2, label="recorded")
        ax.set_title(f"held out {r['held_out_height_m']:.2f} m: {r['inside_95_band']:.0%} inside")
        ax.set_xlabel("force (gf)")
    np.atleast_1d(axes)[0].set_ylabel("displacement (mm)")
    np.atleast_1d(axes)[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=1000, help="MH iterations per chain (main)")
    ap.add_argument("--warmup", type=int, default=100, help="MH warm-up iterations per chain")
    ap.add_argument("--walkers", type=int, default=16, help="MH chains")
    ap.add_argument("--draws", type=int, default=512, help="posterior draws kept for the band")
    ap.add_argument("--seed", type=int, default=0, help="data (logger noise) and sampler seed")
    ap.add_argument(
        "--sampler-seed", type=int, default=None, help="sampler seed alone (default: --seed)"
    )
    ap.add_argument(
        "--sampler",
        choices=("mh", "nuts"),
        default="mh",
        help="mh: the library's Metropolis-Hastings (default); nuts: BlackJAX NUTS with window "
        "adaptation from the Laplace start (--warmup adaptation + --steps draws per chain)",
    )
    ap.add_argument(
        "--laplace",
        choices=("exact", "values"),
        default="exact",
        help="the start and proposal: exact (treeinfer.inference.exact_laplace, default) or values "
        "(treeinfer.inference.problem_laplace, Hessian from differences of values)",
    )
    ap.add_argument(
        "--max-doublings", type=int, default=4, help="NUTS tree depth cap (<= 2^k - 1 leapfrogs)"
    )
    ap.add_argument("--links", type=int, default=8, help="hinged links in the chain (8)")
    ap.add_argument(
        "--hinges",
        choices=("bases", "midpoints", "matched"),
        default="midpoints",
        help="hinge at each segment's base or middle (default), or 'matched': one hinge per "
        "push height at the pseudo-rigid-body pivot, stiffnesses tied to the shape matching the "
        "tapered beam at every push height (treeinfer.tree.matched_hinges; --links "
        "is then the number of heights)",
    )
    ap.add_argument(
        "--tie",
        choices=("taper", "none"),
        default="taper",
        help="the tree file's inference.tie: 'taper' (stiffness along the taper, default) or "
        "'none' (free stiffnesses)",
    )
    ap.add_argument(
        "--tie-scale",
        type=float,
        default=0.1,
        help="soft tie: std of each hinge's log-stiffness about the taper (default 0.1, fixed "
        "a priori: about 2.5%% uncertainty on the diameter, under d^4); 0: hard tie",
    )
    ap.add_argument(
        "--force-noise",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="load-cell noise (estimated from the training forces) read through each pull's "
        "compliance, next to sigma_x (default on; --no-force-noise: sigma_x alone)",
    )
    ap.add_argument(
        "--settle-iterations",
        type=int,
        default=6,
        help="Newton iterations per equilibrium (the solver's convergence check still applies; "
        "5 gave the log-density of 10 to 2e-4 nats at half the cost)",
    )
    ap.add_argument(
        "--folds",
        default="0,1,2",
        help="held-out heights to run, by index (0: 0.12 m, 1: 0.24 m, 2: 0.36 m)",
    )
    ap.add_argument("--out", default="experiments/results/stem_pushes")
    ap.add_argument(
        "--analytic", action="store_true", help="print the model-error table (no sampling) and exit"
    )
    args = ap.parse_args(argv)
    stem = Stem()
    if args.analytic:
        print("\n".join(analytic_table(stem)))
        return
    tie = None if args.tie == "none" else args.tie
    tau = args.tie_scale if (tie is not None and args.tie_scale > 0) else None
    tree = stem_tree(
        stem,
        n_links=args.links,
        kp_bounds=(0.05, 50.0),
        hinges=args.hinges,
        tie=tie,
        tie_scale=tau,
    )
    if args.hinges == "matched":
        args.links = len(tree.inferred)
    # the static model settles and never steps in time: the stability step is enough
    sim = make_simulator(
        tree,
        obs_dt=0.5,
        backend="fused",
        settle_iterations=args.settle_iterations,
        accuracy="coarse",
    )
    with tempfile.TemporaryDirectory() as tmp:
        trajs, pulls, heights = import_logs(Path(tmp), stem, tree, args.seed)
    results = []
    for k in (int(v) for v in args.folds.split(",")):
        results.append(fold(sim, tree, trajs, pulls, heights, k, args))
        r = results[-1]
        print(
            f"held out {r['held_out_height_m']:.2f} m: {r['inside_95_band']:.0%} inside, "
            f"RMSE {1e3 * r['rmse_static_m']:.3f} mm (cantilever "
            f"{1e3 * r['rmse_cantilever_m']:.3f} mm), R-hat max {r['rhat_max']:.3f}, "
            f"{r['sampler_wall_s']:.0f} s",
            flush=True,
        )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(
        out / "results.json",
        json.dumps({"folds": results, "stem": stem._asdict(), "args": vars(args)}) + "\n",
    )
    plot_folds(results, out / "held_out.png")
    if tie is None:
        note = "free stiffnesses"
    elif tau is None:
        note = "stiffness tied along the taper (one scale, hard tie)"
    else:
        note = f"stiffness softly tied along the taper (tau = {tau:g})"
    lines = [
        "| held-out height (m) | inside 95% band | RMSE static (mm) | RMSE cantilever (mm) "
        "| band width (mm) | R-hat max |",
        "|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| {r['held_out_height_m']:.2f} | {r['inside_95_band']:.0%} | "
            f"{1e3 * r['rmse_static_m']:.3f} | {1e3 * r['rmse_cantilever_m']:.3f} | "
            f"{1e3 * r['band_width_mean_m']:.3f} | {r['rhat_max']:.3f} |"
        )
    noise_note = (
        "sigma_x inferred plus the load cell's noise (from the training forces) through each "
        "pull's compliance"
        if args.force_noise
        else "sigma_x inferred"
    )
    lines.append(
        f"\n{args.links} links (hinges at segment {args.hinges}), {note}, static model, Gaussian "
        f"noise: {noise_note}; MH {args.walkers} chains x ({args.warmup} warm-up + "
        f"{args.steps}) steps from a Laplace start, proposal adapted after warm-up; seed "
        f"{args.seed}"
    )
    atomic_write_text(out / "results.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
