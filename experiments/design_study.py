"""Where to pull next: does the pull that ``treeinfer.design`` ranks first teach more?

Protocol, per seed (sim-to-sim, as in the other studies: ground truth from plain MuJoCo C in
float64, inference with the batched simulator):

1. True gains drawn as ``treeinfer simulate`` does (:func:`treeinfer.cli.default_true_params`).
2. **First pull** at the tip (grasp fraction 1), a ramp-hold-release of ``first_peak`` N, with
   white Gaussian noise of ``noise_mm`` on the displacement; posterior 1 by NNSVGD with the
   likelihood temperature of that noise (:func:`treeinfer.likelihood.suggest_kT`).
2. **Score** the candidate second pulls (grasp fractions x peak forces x profile kinds) by the
   Laplace EIG of :func:`treeinfer.design.score_candidates` at posterior 1 (``sigma_x`` = the
   noise).
3. **Four second pulls**, each a new noisy recording: ``design`` (ranked first by EIG),
   ``design_worst`` (ranked first by the expected variance reduction of the parameter with the
   largest std after pull 1, ``score_candidates(..., parameter="worst")``), ``repeat`` (the
   first pull again, fresh noise), ``random`` (a seeded uniform pick among the candidates).
   For each, the posterior of both pulls together (same sampler settings, seed).
4. Report the posterior std (log units) of every parameter after pull 1 and after each second
   pull, and the width of the 95% predictive band at a held-out manipulation (a ramp-hold-release
   of ``heldout_peak`` N at grasp fraction ``heldout_grasp``, not among the candidates),
   averaged over its samples.

Targets (issue 16): the design pull shrinks the std of the worst-identified parameter (largest
std after pull 1) at least 2x more than the repeat (median over seeds), and never widens the
held-out band relative to after pull 1.

Sizes: ``tiny`` (smoke test, 2-branch), ``cpu`` (5 seeds, minutes here), ``full`` (20 seeds,
the paper's particle counts, for a GPU). Results: ``results.json``, ``results.md`` and figures in
``experiments/results/design`` (``full``: ``experiments/results/full/design``).

    python experiments/design_study.py --size cpu
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from experiments.common import (
    RESULTS,
    check_out,
    cpu_seconds,
    reference_trajectory,
    run_main,
    setup_jax,
    tree_path,
    versions,
)

STUDY = "design"
CONDITIONS = ("design", "design_worst", "repeat", "random")


@dataclass(frozen=True)
class DesignConfig:
    """Everything that defines a run of this study (recorded in ``results.json``).

    tree: example name or path. dt, duration: s (sample interval, pull length). seeds: number
    of seeds (0 .. seeds-1, offset by ``--seed``). noise_mm: displacement noise std (mm).
    first_peak: N, the first pull (ramp-hold-release at the tip). grasp_fractions, peak_forces,
    profile_kinds: the candidate grid. heldout_grasp, heldout_peak: the held-out manipulation.
    n_particles, n_iterations: NNSVGD. design_particles: particles the sensitivities are taken at.
    level: credible level of the band.
    """

    size: str
    tree: str = "three_branch"
    dt: float = 0.02
    duration: float = 1.0
    seeds: int = 5
    noise_mm: float = 2.0
    first_peak: float = 5.0
    grasp_fractions: tuple = (0.2, 0.4, 0.6, 0.8, 1.0)
    peak_forces: tuple = (2.0, 4.0, 6.0, 8.0)
    profile_kinds: tuple = ("ramp", "hold")
    heldout_grasp: float = 0.5
    heldout_peak: float = 5.0
    n_particles: int = 24
    n_iterations: int = 100
    design_particles: int = 24
    level: float = 0.95


SIZES = {
    "tiny": {
        "tree": "two_branch",
        "duration": 0.6,
        "seeds": 2,
        "grasp_fractions": (0.4, 1.0),
        "peak_forces": (1.0, 6.0),
        "profile_kinds": ("hold",),
        "n_particles": 8,
        "n_iterations": 10,
        "design_particles": 8,
    },
    "cpu": {
        "profile_kinds": ("ramp", "hold", "step"),
        "n_particles": 24,
        "n_iterations": 120,
        "design_particles": 24,
    },
    "full": {
        "dt": 0.01,
        "duration": 2.0,
        "seeds": 20,
        "grasp_fractions": tuple(np.round(np.linspace(0.1, 1.0, 10), 2)),
        "peak_forces": (2.0, 4.0, 6.0, 8.0, 10.0),
        "profile_kinds": ("ramp", "hold", "step"),
        "n_particles": 128,
        "n_iterations": 300,
        "design_particles": 64,
    },
}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python experiments/design_study.py",
        description=__doc__.split("\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--size",
        choices=tuple(SIZES),
        default="cpu",
        help="tiny, cpu (5 seeds) or full (20 seeds, GPU)",
    )
    p.add_argument("--seeds", type=int, default=None, help="override the number of seeds")
    p.add_argument("--seed", type=int, default=0, help="first seed (default 0)")
    p.add_argument("--particles", type=int, default=None, help="override NNSVGD's particle count")
    p.add_argument("--iterations", type=int, default=None, help="override NNSVGD's iteration count")
    p.add_argument("--out", type=Path, default=None, help="results folder")
    p.add_argument("--quiet", action="store_true")
    p.add_argument(
        "--resummarise",
        action="store_true",
        help="recompute the summary, markdown and figures of --out's results.json (no inference)",
    )
    return p


def _say(quiet: bool, msg: str) -> None:
    if not quiet:
        print(f"[{STUDY}] {msg}", file=sys.stderr, flush=True)


# ==== one seed ====================================================================================
def _pull(sim, kp, kd, cand, cfg: DesignConfig, rng, name: str):
    """A noisy recording of candidate ``cand`` (ground truth from MuJoCo C)."""
    from treeinfer.design import candidate_forces
    from treeinfer.trajectories import add_noise

    force = candidate_forces([cand], cfg.duration, cfg.dt)[0]
    clean = reference_trajectory(sim, kp, kd, force, cfg.dt, name, cand.grasp_fraction)
    return add_noise(clean, 0.0, cfg.noise_mm * 1e-3, rng)._replace(source=name)


class _Post:
    """Final particles ``theta [P, D]``, their log-density and ``valid`` (finite) mask."""

    def __init__(self, theta, logdensity):
        self.theta, self.log_density = np.asarray(theta), np.asarray(logdensity)
        self.valid = np.isfinite(self.log_density) & np.all(np.isfinite(self.theta), 1)


_RUNNERS: dict = {}


def _runner(tree, sim, kT: float, cfg: DesignConfig, n_pulls: int):
    """NNSVGD on ``n_pulls`` recordings, compiled once and reused for every seed and condition.

    The same problem (:func:`treeinfer.inference.make_problem`), algorithm
    (``Problem.sampler`` / ``inference.make_algorithm``), initial particles and per-iteration keys
    as :func:`treeinfer.inference.infer`, but the recordings are arguments of one jitted
    ``lax.scan`` instead of constants closed over, so that a new data set does not recompile
    (on a 2-core CPU a compile costs more than the run)."""
    key_ = (id(sim), kT, n_pulls, cfg.n_particles, cfg.n_iterations)
    if key_ in _RUNNERS:
        return _RUNNERS[key_]
    import jax

    from treeinfer import inference
    from treeinfer.inference import make_problem
    from treeinfer.samplers import init_key, iteration_key
    from treeinfer.trajectories import Observations

    @jax.jit
    def run(theta0, key, force, disp, vel, mask, grasp):
        obs = Observations(force, disp, vel, mask, float(cfg.dt))
        problem = make_problem(tree, obs, kT=kT, sim=sim, grasp_fraction=grasp)
        if hasattr(problem, "sampler"):  # after the refactor: Problem.sampler(name)
            alg = problem.sampler("nnsvgd")
        else:
            alg = inference.make_algorithm(problem, "nnsvgd")
        state = alg.init(init_key(key), theta0)
        state, _ = jax.lax.scan(
            lambda st, i: (alg.step(iteration_key(key, i), st)[0], None),
            state,
            jax.numpy.arange(cfg.n_iterations),
        )
        return state.position, state.logdensity

    _RUNNERS[key_] = run
    return run


def _posterior(tree, sim, trajs, grasp, kT, cfg: DesignConfig, seed: int) -> _Post:
    import jax

    from treeinfer.inference import initial_particles, make_problem
    from treeinfer.trajectories import stack_trajectories

    obs = stack_trajectories(trajs)
    template = make_problem(
        tree, obs, kT=kT, sim=sim, nn_prior=False
    )  # box only: for the initial particles
    theta0 = initial_particles(template, cfg.n_particles, seed)
    run = _runner(tree, sim, kT, cfg, len(trajs))
    f32 = lambda a: np.asarray(a, np.float32)
    theta, ld = run(
        theta0,
        jax.random.key(int(seed)),
        f32(obs.force),
        f32(obs.displacement),
        f32(obs.velocity),
        np.asarray(obs.mask),
        f32(grasp),
    )
    return _Post(theta, ld)


def _band_width(sim, theta, valid, force, grasp, level) -> float:
    """Mean over time of the ``level`` predictive band's width (m) at the held-out manipulation."""
    from treeinfer.inference import predict
    from treeinfer.metrics import predictive_interval

    r = predict(sim, theta, force[None], grasp_fraction=np.array([grasp]))
    ok = np.asarray(r.stable[:, 0]) & np.asarray(valid)
    lo, hi, _ = predictive_interval(np.asarray(r.tau[:, 0]), level=level, valid=ok)
    return float(np.mean(np.asarray(hi) - np.asarray(lo)))


def run_seed(cfg: DesignConfig, tree, sim, seed: int, quiet: bool) -> dict:
    try:  # the application-layer refactor moves it to treeinfer.synthetic
        from treeinfer.synthetic import default_true_params
    except ImportError:
        from treeinfer.cli import default_true_params
    from treeinfer.design import Candidate, candidate_forces, candidate_grid, score_candidates
    from treeinfer.likelihood import suggest_kT

    streams = [
        np.random.default_rng(s)
        for s in np.random.SeedSequence([int(seed), 0xDE51]).spawn(3 + len(CONDITIONS))
    ]
    kp, kd = default_true_params(tree, streams[0])
    t_steps = round(cfg.duration / cfg.dt)
    kT = suggest_kT(cfg.noise_mm * 1e-3, t_steps, cfg.dt)
    first = Candidate(1.0, cfg.first_peak, "hold")
    traj1 = _pull(sim, kp, kd, first, cfg, streams[1], "first")
    t0 = time.perf_counter()
    post1 = _posterior(tree, sim, [traj1], [1.0], kT, cfg, seed)
    _say(quiet, f"seed {seed}: posterior 1 in {time.perf_counter() - t0:.0f} s")
    cands = candidate_grid(cfg.grasp_fractions, cfg.peak_forces, cfg.profile_kinds)
    t0 = time.perf_counter()
    sugg = score_candidates(
        sim,
        post1.theta,
        cands,
        cfg.noise_mm * 1e-3,
        cfg.duration,
        valid=post1.valid,
        n_particles=cfg.design_particles,
        seed=seed,
    )
    t_design = time.perf_counter() - t0
    sugg_worst = score_candidates(
        sim,
        post1.theta,
        cands,
        cfg.noise_mm * 1e-3,
        cfg.duration,
        valid=post1.valid,
        n_particles=cfg.design_particles,
        seed=seed,
        parameter="worst",
    )
    pick = cands[int(streams[2].integers(len(cands)))]
    seconds = {
        "design": sugg.best,
        "design_worst": sugg_worst.best,
        "repeat": first,
        "random": pick,
    }
    held_force = candidate_forces(
        [Candidate(cfg.heldout_grasp, cfg.heldout_peak, "hold")], cfg.duration, cfg.dt
    )[0]
    out = {
        "seed": seed,
        "true_theta": np.log(np.concatenate([kp, kd])).tolist(),
        "kT": kT,
        "design_seconds": t_design,
        "design_top5": sugg.to_dict()["candidates"][:5],
        "design_worst_parameter": sugg_worst.settings["parameter"],
        "design_worst_top5": sugg_worst.to_dict()["candidates"][:5],
        "stages": {},
    }

    def record(name, post, cand):
        v = post.valid
        th = post.theta[v]
        out["stages"][name] = {
            "second_pull": None if cand is None else cand.to_dict(),
            "mean": th.mean(0).tolist(),
            "std": th.std(0, ddof=1).tolist(),
            "band_width_m": _band_width(
                sim, post.theta, v, held_force, cfg.heldout_grasp, cfg.level
            ),
            "n_valid": int(v.sum()),
        }

    record("first", post1, None)
    for i, cond in enumerate(CONDITIONS):
        cand = seconds[cond]
        traj2 = _pull(sim, kp, kd, cand, cfg, streams[3 + i], f"second_{cond}")
        t0 = time.perf_counter()
        post = _posterior(tree, sim, [traj1, traj2], [1.0, cand.grasp_fraction], kT, cfg, seed)
        _say(
            quiet,
            f"seed {seed}: {cond} ({cand.grasp_fraction:g}, {cand.peak_force:g} N, "
            f"{cand.profile_kind}) "
            f"in {time.perf_counter() - t0:.0f} s",
        )
        record(cond, post, cand)
    return out, sugg


# ==== summary =====================================================================================
def summarise(seeds: list[dict], labels) -> dict:
    std = {
        s: np.array([r["stages"][s]["std"] for r in seeds]) for s in ("first",) + CONDITIONS
    }  # [S, D]
    band = {
        s: np.array([r["stages"][s]["band_width_m"] for r in seeds])
        for s in ("first",) + CONDITIONS
    }
    worst = np.argmax(std["first"], axis=1)  # per seed: the worst-identified parameter after pull 1
    rows = np.arange(len(seeds))
    shrink = {c: std["first"][rows, worst] - std[c][rows, worst] for c in CONDITIONS}
    med = {c: float(np.median(shrink[c])) for c in CONDITIONS}
    # the target: design's median shrink >= 2x repeat's (a repeat that shrinks nothing or widens
    # the std counts as 0, and the design must shrink it at all); the ratio is None then
    ratio = med["design"] / med["repeat"] if med["repeat"] > 0 else None
    ratio_w = med["design_worst"] / med["repeat"] if med["repeat"] > 0 else None
    met = lambda c: bool(med[c] > 0 and med[c] >= 2.0 * max(med["repeat"], 0.0))
    return {
        "labels": list(labels),
        "median_std": {s: np.median(v, 0).tolist() for s, v in std.items()},
        "worst_parameter_per_seed": [labels[i] for i in worst],
        "worst_std_shrink_per_seed": {c: shrink[c].tolist() for c in CONDITIONS},
        "median_worst_std_shrink": med,
        "design_vs_repeat_shrink_ratio": ratio,
        "target_2x_more_shrink_than_repeat": met("design"),
        "design_worst_vs_repeat_shrink_ratio": ratio_w,
        "design_worst_target_2x": met("design_worst"),
        "design_worst_never_widens_band": bool(np.all(band["design_worst"] <= band["first"])),
        "band_width_m_per_seed": {s: v.tolist() for s, v in band.items()},
        "median_band_width_m": {s: float(np.median(v)) for s, v in band.items()},
        "design_never_widens_band": bool(np.all(band["design"] <= band["first"])),
        "seeds_where_design_widens_band": [
            r["seed"] for r, a, b in zip(seeds, band["design"], band["first"]) if a > b
        ],
    }


def _figures(summary: dict, sugg):
    import matplotlib.pyplot as plt

    from treeinfer.design import plot_scores

    labels = summary["labels"]
    stages = ("first",) + CONDITIONS
    fig1, ax = plt.subplots(figsize=(1.4 * len(labels) + 3, 3.6))
    x = np.arange(len(labels))
    wbar = 0.8 / len(stages)
    for i, s in enumerate(stages):
        ax.bar(
            x + (i - (len(stages) - 1) / 2) * wbar,
            summary["median_std"][s],
            wbar,
            label="after pull 1" if s == "first" else f"+ {s}",
        )
    ax.set_xticks(x, labels, rotation=20)
    ax.set_ylabel("posterior std [log units] (median over seeds)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    fig1.tight_layout()
    fig2, ax2 = plt.subplots(figsize=(5, 3.6))
    bw = summary["band_width_m_per_seed"]
    for j in range(len(bw["first"])):
        ax2.plot(range(len(stages)), [1e3 * bw[s][j] for s in stages], "o-", color="0.6", lw=0.8)
    ax2.plot(
        range(len(stages)),
        [1e3 * summary["median_band_width_m"][s] for s in stages],
        "k*-",
        ms=10,
        label="median",
    )
    ax2.set_xticks(range(len(stages)), ["pull 1"] + [f"+{c}" for c in CONDITIONS], rotation=15)
    ax2.set_ylabel("held-out 95% band width [mm]")
    ax2.set_yscale("log")
    ax2.legend()
    ax2.grid(alpha=0.3)
    fig2.tight_layout()
    fig3, _ = plot_scores(sugg)
    return {"std.png": fig1, "band.png": fig2, "scores_seed0.png": fig3}


def _ratio(r) -> str:
    return "n/a (repeat did not shrink it)" if r is None else f"{r:.2f}"


def _markdown(
    cfg: DesignConfig, summary: dict, seeds: list[dict], wall: float, cpu: float | None = None
) -> str:
    labels = summary["labels"]
    lines = [
        f"# Design study ({cfg.size}): which second pull?",
        "",
        (
            f"Tree `{cfg.tree}`, {cfg.seeds} seeds, displacement noise {cfg.noise_mm:g} mm, "
            "first pull: "
            f"ramp-hold-release {cfg.first_peak:g} N at the tip; "
            f"NNSVGD {cfg.n_particles} particles x "
            f"{cfg.n_iterations} iterations; candidates: grasp {list(cfg.grasp_fractions)} x peak "
            f"{list(cfg.peak_forces)} N x {list(cfg.profile_kinds)}; "
            f"held-out: {cfg.heldout_peak:g} N hold at grasp "
            f"{cfg.heldout_grasp:g}. dt {cfg.dt:g} s, {cfg.duration:g} s pulls."
        ),
        "",
        "## Posterior std (log units), median over seeds",
        "",
        "| stage | " + " | ".join(labels) + " | held-out band [mm] |",
        "|---" * (len(labels) + 2) + "|",
    ]
    for s in ("first",) + CONDITIONS:
        name = "after pull 1" if s == "first" else f"+ {s}"
        cells = " | ".join(f"{v:.3f}" for v in summary["median_std"][s])
        lines.append(f"| {name} | {cells} | {1e3 * summary['median_band_width_m'][s]:.2f} |")
    m = summary["median_worst_std_shrink"]
    lines += [
        "",
        "## Targets",
        "",
        (
            "- Worst-identified parameter after pull 1 (per seed): "
            f"{', '.join(summary['worst_parameter_per_seed'])}."
        ),
        (
            f"- Median shrink of its std: design {m['design']:.3f}, "
            f"design_worst {m['design_worst']:.3f}, "
            f"repeat {m['repeat']:.3f}, random {m['random']:.3f} (log units); design / repeat = "
            f"{_ratio(summary['design_vs_repeat_shrink_ratio'])} (target >= 2: "
            f"**{'met' if summary['target_2x_more_shrink_than_repeat'] else 'not met'}**); "
            "design_worst / repeat = "
            f"{_ratio(summary['design_worst_vs_repeat_shrink_ratio'])} "
            f"(**{'met' if summary['design_worst_target_2x'] else 'not met'}**)."
        ),
        (
            f"- design_worst never widens the held-out band: "
            f"**{'yes' if summary['design_worst_never_widens_band'] else 'no'}**."
        ),
        "- Design pull never widens the held-out band: "
        f"**{'yes' if summary['design_never_widens_band'] else 'no'}**"
        + (
            f" (wider at seeds {summary['seeds_where_design_widens_band']})"
            if summary["seeds_where_design_widens_band"]
            else ""
        )
        + ".",
        "",
        "## Second pulls chosen",
        "",
        (
            "| seed | design (grasp, N, kind) | design_worst (parameter) | random "
            "| EIG of best [nats] | scoring [s] |"
        ),
        "|---|---|---|---|---|---|",
    ]
    fmt = lambda c: f"{c['grasp_fraction']:g}, {c['peak_force']:g}, {c['profile_kind']}"
    for r in seeds:
        st = r["stages"]
        lines.append(
            f"| {r['seed']} | {fmt(st['design']['second_pull'])} "
            f"| {fmt(st['design_worst']['second_pull'])} "
            f"({r['design_worst_parameter']}) | {fmt(st['random']['second_pull'])} | "
            f"{r['design_top5'][0]['score']:.2f} | {r['design_seconds']:.1f} |"
        )
    lines += [
        "",
        f"Wall time {wall:.0f} s, process CPU time {cpu_seconds() if cpu is None else cpu:.0f} s.",
        "",
    ]
    return "\n".join(lines)


def _suggestions_from_dict(d: dict):
    """A :class:`~treeinfer.design.Suggestions` back from its ``to_dict()`` (for the figure)."""
    from treeinfer.design import Candidate, Suggestions

    rows = d["candidates"]
    cands = tuple(
        Candidate(
            r["grasp_fraction"],
            r["peak_force"],
            r["profile_kind"],
            None if r["direction"] is None else tuple(r["direction"]),
        )
        for r in rows
    )
    num = lambda k: np.array([np.nan if r.get(k) is None else r[k] for r in rows], float)
    return Suggestions(
        cands,
        num("score"),
        num("stable_share"),
        None,
        None,
        tuple(r["spec"] for r in rows),
        d["settings"],
    )


def _resummarise(out: Path) -> int:
    """Recompute summary, markdown and figures from ``out/results.json`` (no inference)."""
    import json

    from treeinfer._io import atomic_write_json, atomic_write_text, staged_output_dir
    from treeinfer.plots import save_figure

    record = json.loads((out / "results.json").read_text())
    sugg_d = json.loads((out / "suggestions_seed0.json").read_text())
    cfg = DesignConfig(
        **{k: tuple(v) if isinstance(v, list) else v for k, v in record["config"].items()}
    )
    seeds = record["seeds"]
    record["summary"] = summarise(seeds, record["summary"]["labels"])
    md = _markdown(cfg, record["summary"], seeds, record["wall_time_s"], record["cpu_time_s"])
    figures = _figures(record["summary"], _suggestions_from_dict(sugg_d))
    with staged_output_dir(out, force=True, what="results") as stage:
        for name, fig in figures.items():
            save_figure(fig, stage / name)
        atomic_write_json(stage / "results.json", record)
        atomic_write_text(stage / "results.md", md)
        atomic_write_json(stage / "suggestions_seed0.json", sugg_d)
    print(md)
    return 0


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    over = {
        k: v
        for k, v in (
            ("seeds", args.seeds),
            ("n_particles", args.particles),
            ("n_iterations", args.iterations),
        )
        if v is not None
    }
    cfg = DesignConfig(size=args.size, **{**SIZES[args.size], **over})
    out = args.out or (RESULTS / "full" / STUDY if args.size == "full" else RESULTS / STUDY)
    check_out(out)
    if args.resummarise:
        return _resummarise(Path(out))
    setup_jax()
    from treeinfer import make_simulator
    from treeinfer._io import atomic_write_json, atomic_write_text, staged_output_dir
    from treeinfer.plots import save_figure
    from treeinfer.tree import load_tree

    t0 = time.perf_counter()
    tree = load_tree(tree_path(cfg.tree))
    sim = make_simulator(tree, obs_dt=cfg.dt)
    seeds, first_sugg = [], None
    for s in range(args.seed, args.seed + cfg.seeds):
        rec, sugg = run_seed(cfg, tree, sim, s, args.quiet)
        seeds.append(rec)
        first_sugg = first_sugg or sugg
    summary = summarise(seeds, tree.parameter_labels())
    wall = time.perf_counter() - t0
    record = {
        "study": STUDY,
        "size": cfg.size,
        "first_seed": args.seed,
        "config": dataclasses.asdict(cfg),
        "versions": versions(),
        "command": " ".join(["experiments/design_study.py"] + list(argv or sys.argv[1:])),
        "summary": summary,
        "seeds": seeds,
        "wall_time_s": wall,
        "cpu_time_s": cpu_seconds(),
    }
    figures = _figures(summary, first_sugg)
    with staged_output_dir(out, force=True, what="results") as stage:
        for name, fig in figures.items():
            save_figure(fig, stage / name)
        atomic_write_json(stage / "results.json", record)
        atomic_write_text(stage / "results.md", _markdown(cfg, summary, seeds, wall, cpu_seconds()))
        atomic_write_json(stage / "suggestions_seed0.json", first_sugg.to_dict())
    _say(args.quiet, f"wrote {out} in {wall:.0f} s")
    print(_markdown(cfg, summary, seeds, wall))
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main, sys.argv[1:], STUDY))
