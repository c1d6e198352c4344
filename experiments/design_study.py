"""Where to pull next: does the pull that ``treeinfer.design`` ranks first teach more?

Protocol, per seed (sim-to-sim, as in the other studies: ground truth from plain MuJoCo C in
float64, inference with the batched simulator):

1. True gains drawn as ``treeinfer simulate`` does
   (:func:`treeinfer.synthetic.default_true_params`).
2. **First pull** at the tip (grasp fraction 1), a ramp-hold-release (``hold`` profile) of
   ``first_peak`` N, with white Gaussian noise of ``noise_mm`` on the displacement; posterior 1
   by NNSVGD with the likelihood temperature of that noise, velocity term included
   (:func:`treeinfer.likelihood.suggest_kT` with ``omega2`` of the data set).
3. **Score** the candidate second pulls (grasp fractions x peak forces x profile kinds) at
   posterior 1 (``sigma_x`` = the noise) with :func:`treeinfer.design.score_candidates`.
4. **Second pulls**, each a new noisy recording: ``design`` (ranked first by the Laplace EIG),
   ``design_target`` (ranked first by the expected reduction of the held-out manipulation's
   predictive variance, ``target=``: the criterion to use when the future manipulation is known),
   ``design_worst`` (ranked first by the expected variance reduction of the parameter with the
   largest std after pull 1, ``parameter="worst"``), ``repeat`` (the first pull again, fresh
   noise), ``random`` (a seeded uniform pick among the candidates). For each, the posterior of
   both pulls together, with the same inference settings and sampler seed as every other arm.
5. Report the posterior std (log units) of every parameter after pull 1 and after each second
   pull, and the width of the 95% predictive band at the held-out manipulation (a ``hold`` pull
   of ``heldout_peak`` N at grasp fraction ``heldout_grasp``, not among the candidates), averaged
   over its samples. Beside them, as an independent reference, the Cramér-Rao std of every
   parameter and the linearised held-out band (``3.92 sqrt(G C G^T)``) from the Fisher
   information of the pulls at the true parameters (Gaussian noise of ``noise_mm``).

**Inference (why not the uniform start).** NNSVGD from particles uniform in the prior box with a
constant Adam step (the settings of the first version of this study) is far from converged
here: on identical data, three sampler seeds gave held-out bands of 22, 182 and 207 mm and
particles 150 nats below the best one, while the Fisher information at the truth gives a band
of ~4 mm; the arms' bands then differed by sampler noise, not by their data. So every posterior
here (all arms alike) starts from draws of the Laplace approximation around a Levenberg-Marquardt
MAP fit of *its own* data (:func:`treeinfer.mapfit.fit_map`, as ``treeinfer infer --init
laplace``; widened ``laplace_scale`` x), and NNSVGD's Adam step decays along a cosine from
``learning_rate`` to ``final_learning_rate`` so the particles settle (``init="uniform"`` and
``final_learning_rate=None`` give the old behaviour). The first version also set kT for the
displacement term alone (``omega2 = 0``), which leaves the velocity term of the loss untempered:
its posteriors came out ~3-4x narrower than the Cramér-Rao bound (``kT_velocity``). All
posteriors of a stage run as one batched program
(:func:`treeinfer.batch_posteriors.posterior_program`, ``batch`` data sets per call).

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

from experiments.common import (  # noqa: E402
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
# compiled batched programs, reused across seeds and stages of this process (the study owns it)
_PROGRAMS: dict = {}
from experiments._design_summary import CONDITIONS  # noqa: E402


@dataclass(frozen=True)
class DesignConfig:
    """Everything that defines a run of this study (recorded in ``results.json``).

    tree: example name or path. dt, duration: s (sample interval, pull length). seeds: number
    of seeds (0 .. seeds-1, offset by ``--seed``). noise_mm: displacement noise std (mm).
    first_peak: N, the first pull (ramp-hold-release at the tip). grasp_fractions, peak_forces,
    profile_kinds: the candidate grid. heldout_grasp, heldout_peak: the held-out manipulation.
    n_particles, n_iterations: NNSVGD. design_particles: particles the sensitivities are taken at.
    level: credible level of the band. init: ``"laplace"`` (MAP fit of each data set, its
    Laplace draws widened ``laplace_scale`` x; ``map_starts`` LM starts, ``map_iterations``) or
    ``"uniform"`` (the prior box). learning_rate, final_learning_rate: NNSVGD's Adam step and
    where its cosine decay ends (None: constant). batch: data sets per batched sampler call.
    kT_velocity: each data set's temperature counts the velocity term of the loss
    (``suggest_kT(sigma, T, dt, signal_omega2(obs, sigma))``, as ``kT="auto"`` with the noise
    known); False: ``suggest_kT(sigma, T, dt)``, which tempers the displacement term only.
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
    init: str = "laplace"
    laplace_scale: float = 2.0
    map_starts: int = 6
    map_iterations: int = 25
    learning_rate: float = 0.1
    final_learning_rate: float | None = 0.003
    batch: int = 128
    kT_velocity: bool = True


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
        "map_starts": 2,
        "map_iterations": 5,
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
        "grasp_fractions": tuple(float(g) for g in np.round(np.linspace(0.1, 1.0, 10), 2)),
        "peak_forces": (2.0, 4.0, 6.0, 8.0, 10.0),
        "profile_kinds": ("ramp", "hold", "step"),
        # 256 x 1000: at 128 x 300 one of 20 design posteriors had not converged (best minus
        # median log density 12 nats) and its held-out band came out 1.2% wider than before.
        "n_particles": 256,
        "n_iterations": 1000,
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
    p.add_argument(
        "--init",
        choices=("laplace", "uniform"),
        default=None,
        help="particle start of every posterior (default laplace: MAP fit + Laplace draws)",
    )
    p.add_argument(
        "--batch", type=int, default=None, help="data sets per batched sampler call (default 128)"
    )
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


# ==== data, posteriors, references ================================================================
def _pull(sim, kp, kd, cand, cfg: DesignConfig, rng, name: str):
    """A noisy recording of candidate ``cand`` (ground truth from MuJoCo C)."""
    from treeinfer.design import candidate_forces
    from treeinfer.trajectories import add_noise

    force = candidate_forces([cand], cfg.duration, cfg.dt)[0]
    clean = reference_trajectory(sim, kp, kd, force, cfg.dt, name, cand.grasp_fraction)
    return add_noise(clean, 0.0, cfg.noise_mm * 1e-3, rng)._replace(source=name)


class _Post:
    """Final particles ``theta [P, D]``, their log-density and ``valid`` (finite) mask."""

    def __init__(self, theta, logdensity, kT=None):
        self.theta, self.log_density = np.asarray(theta), np.asarray(logdensity)
        self.kT = kT
        self.valid = np.isfinite(self.log_density) & np.all(np.isfinite(self.theta), 1)


def _kT(obs, cfg: DesignConfig) -> float:
    """The data set's Boltzmann temperature for the study's noise (see ``kT_velocity``)."""
    from treeinfer.likelihood import signal_omega2, suggest_kT

    sigma = cfg.noise_mm * 1e-3
    omega2 = signal_omega2(obs, sigma) if cfg.kT_velocity else 0.0
    return suggest_kT(sigma, int(np.shape(obs.displacement)[-1]), cfg.dt, omega2)


def _starts(tree, sim, kts, obs, grasp, seeds, cfg: DesignConfig) -> list[np.ndarray]:
    """``[P, D]`` starting particles of each posterior (see the module docstring): Laplace draws
    around a MAP fit of each data set (:func:`treeinfer.batch_posteriors.map_fits`: mapfit's
    Levenberg-Marquardt fit, all data sets in one compiled program), or uniform in the box."""
    import jax

    from treeinfer.batch_posteriors import map_fits
    from treeinfer.inference import initial_particles, make_problem
    from treeinfer.mapfit import laplace_particles

    if cfg.init == "uniform":
        problem = make_problem(tree, obs[0], kT=1.0, sim=sim, nn_prior=False)
        return [np.asarray(initial_particles(problem, cfg.n_particles, s)) for s in seeds]
    out = []
    for i in range(0, len(obs), cfg.batch):
        part = slice(i, i + cfg.batch)
        fits = map_fits(
            tree,
            sim,
            kts[part],
            obs[part],
            np.asarray(grasp[part], np.float32),
            n_starts=cfg.map_starts,
            seeds=seeds[part],
            max_iterations=cfg.map_iterations,
            cache=_PROGRAMS,
        )
        for fit, s in zip(fits, seeds[part]):
            key = jax.random.fold_in(jax.random.key(int(s)), 0x1A9)
            draws = laplace_particles(key, fit, cfg.n_particles, scale=cfg.laplace_scale)
            out.append(np.asarray(draws))
    return out


def _posteriors(tree, sim, jobs: list, cfg: DesignConfig) -> list[_Post]:
    """Posteriors of ``jobs`` = [(trajectories, grasp fractions, seed)], all with the same
    number of pulls, through one batched NNSVGD program (``cfg.batch`` data sets per call)."""
    from treeinfer.batch_posteriors import posterior_program, run_posteriors
    from treeinfer.trajectories import stack_trajectories

    program = posterior_program(
        tree,
        sim,
        cfg.n_iterations,
        learning_rate=cfg.learning_rate,
        final_learning_rate=cfg.final_learning_rate,
        cache=_PROGRAMS,
    )
    obs = [stack_trajectories(trajs) for trajs, _, _ in jobs]
    kts = [_kT(o, cfg) for o in obs]
    grasp = [g for _, g, _ in jobs]
    seeds = [s for _, _, s in jobs]
    theta0 = _starts(tree, sim, kts, obs, grasp, seeds, cfg)
    out = []
    for i in range(0, len(jobs), cfg.batch):
        part = slice(i, i + cfg.batch)
        theta, ld = run_posteriors(
            program,
            np.stack(theta0[part]),
            seeds[part],
            kts[part],
            obs[part],
            np.asarray(grasp[part], np.float32),
        )
        out += [_Post(t, v, k) for t, v, k in zip(theta, ld, kts[part])]
    return out


def _band_width(sim, theta, valid, force, grasp, level) -> float:
    """Mean over time of the ``level`` predictive band's width (m) at the held-out manipulation."""
    from treeinfer.inference import predict
    from treeinfer.metrics import predictive_interval

    r = predict(sim, theta, force[None], grasp_fraction=np.array([grasp]))
    ok = np.asarray(r.stable[:, 0]) & np.asarray(valid)
    lo, hi, _ = predictive_interval(np.asarray(r.tau[:, 0]), level=level, valid=ok)
    return float(np.mean(np.asarray(hi) - np.asarray(lo)))


def _fisher_reference(sim, theta_true, cands, cfg: DesignConfig) -> dict:
    """Cramér-Rao std [D] (log units) and linearised held-out band (m) after pull 1 and after
    pull 1 + each candidate in ``cands`` (a dict name -> Candidate), from the Gaussian Fisher
    information ``J^T J / sigma^2`` at the true parameters (central differences, step 1e-2)."""
    import jax.numpy as jnp

    from treeinfer.design import Candidate, candidate_forces, fd_jacobian, simulator_forward

    held = Candidate(cfg.heldout_grasp, cfg.heldout_peak, "hold")
    names = list(cands)
    allc = [cands[n] for n in names] + [held]
    forces = candidate_forces(allc, cfg.duration, cfg.dt)
    grasp = np.asarray([c.grasp_fraction for c in allc], np.float32)
    fwd = simulator_forward(sim, forces, grasp)
    jac, ok = fd_jacobian(fwd, jnp.asarray(theta_true, np.float32)[None], rel_step=1e-2)
    jac = np.asarray(jac, float)[0]  # [C, T, D]
    sig2 = (cfg.noise_mm * 1e-3) ** 2
    fisher = {n: jac[i].T @ jac[i] / sig2 for i, n in enumerate(names)}
    g = jac[-1]
    out = {}
    for n in names:
        f = fisher[names[0]] + (0.0 if n == names[0] else fisher[n])
        cov = np.linalg.pinv(f)
        band = 3.92 * np.mean(np.sqrt(np.clip(np.einsum("td,de,te->t", g, cov, g), 0, None)))
        out[n] = {
            "crb_std": np.sqrt(np.clip(np.diag(cov), 0, None)).tolist(),
            "crb_band_m": float(band),
            "stable": bool(np.all(np.asarray(ok))),
        }
    return out


def run_seeds(cfg: DesignConfig, tree, sim, seeds: list[int], quiet: bool):
    """The study for ``seeds``: returns ``(per-seed records, suggestions of the first seed)``."""
    from treeinfer.design import (
        Candidate,
        Target,
        candidate_forces,
        candidate_grid,
        score_candidates,
    )
    from treeinfer.synthetic import default_true_params

    first = Candidate(1.0, cfg.first_peak, "hold")
    cands = candidate_grid(cfg.grasp_fractions, cfg.peak_forces, cfg.profile_kinds)
    target = Target(cfg.heldout_grasp, cfg.heldout_peak, "hold")
    held_force = candidate_forces([target.candidate()], cfg.duration, cfg.dt)[0]
    data = {}
    for seed in seeds:
        streams = [
            np.random.default_rng(s)
            for s in np.random.SeedSequence([int(seed), 0xDE51]).spawn(3 + len(CONDITIONS))
        ]
        kp, kd = default_true_params(tree, streams[0])
        data[seed] = (kp, kd, streams, _pull(sim, kp, kd, first, cfg, streams[1], "first"))
    t0 = time.perf_counter()
    post1 = _posteriors(tree, sim, [([data[s][3]], [1.0], s) for s in seeds], cfg)
    _say(quiet, f"posterior 1 of {len(seeds)} seeds in {time.perf_counter() - t0:.0f} s")
    records, jobs, first_sugg = {}, [], None
    for seed, p1 in zip(seeds, post1):
        kp, kd, streams, traj1 = data[seed]
        common = dict(valid=p1.valid, n_particles=cfg.design_particles, seed=seed)
        sigma = cfg.noise_mm * 1e-3
        t0 = time.perf_counter()
        sugg = score_candidates(sim, p1.theta, cands, sigma, cfg.duration, **common)
        t_design = time.perf_counter() - t0
        sugg_t = score_candidates(
            sim, p1.theta, cands, sigma, cfg.duration, target=target, **common
        )
        sugg_w = score_candidates(
            sim, p1.theta, cands, sigma, cfg.duration, parameter="worst", **common
        )
        first_sugg = first_sugg or sugg
        seconds = {
            "design": sugg.best,
            "design_target": sugg_t.best,
            "design_worst": sugg_w.best,
            "repeat": first,
            "random": cands[int(streams[2].integers(len(cands)))],
        }
        theta_true = np.log(np.concatenate([kp, kd]))
        records[seed] = {
            "seed": seed,
            "true_theta": theta_true.tolist(),
            "design_seconds": t_design,
            "design_top5": sugg.to_dict()["candidates"][:5],
            "design_target_top5": sugg_t.to_dict()["candidates"][:5],
            "design_worst_parameter": sugg_w.settings["parameter"],
            "design_worst_top5": sugg_w.to_dict()["candidates"][:5],
            "fisher_reference": _fisher_reference(
                sim, theta_true, {"first": first, **seconds}, cfg
            ),
            "stages": {},
        }
        records[seed]["stages"]["first"] = _stage(sim, p1, None, held_force, cfg)
        for i, cond in enumerate(CONDITIONS):
            cand = seconds[cond]
            traj2 = _pull(sim, kp, kd, cand, cfg, streams[3 + i], f"second_{cond}")
            jobs.append((seed, cond, cand, ([traj1, traj2], [1.0, cand.grasp_fraction], seed)))
    t0 = time.perf_counter()
    post2 = _posteriors(tree, sim, [j[3] for j in jobs], cfg)
    _say(quiet, f"{len(jobs)} second-pull posteriors in {time.perf_counter() - t0:.0f} s")
    for (seed, cond, cand, _), p in zip(jobs, post2):
        records[seed]["stages"][cond] = _stage(sim, p, cand, held_force, cfg)
    return [records[s] for s in seeds], first_sugg


def _stage(sim, post: _Post, cand, held_force, cfg: DesignConfig) -> dict:
    v = post.valid
    th, ld = post.theta[v], post.log_density[v]
    return {
        "second_pull": None if cand is None else cand.to_dict(),
        "mean": th.mean(0).tolist(),
        "std": th.std(0, ddof=1).tolist(),
        "band_width_m": _band_width(sim, post.theta, v, held_force, cfg.heldout_grasp, cfg.level),
        "n_valid": int(v.sum()),
        "kT": post.kT,
        # convergence: how far the median particle sits below the best one (nats); a converged
        # posterior in D dimensions has about D/2 (chi-square), a stuck one hundreds
        "log_density_max_minus_median": float(np.max(ld) - np.median(ld)) if len(ld) else None,
    }


# summary, figures and markdown: experiments/_design_summary.py
from experiments._design_summary import (  # noqa: E402
    _figures,
    _markdown,
    _suggestions_from_dict,
    summarise,
)


def _resummarise(out: Path) -> int:
    """Recompute summary, markdown and figures from ``out/results.json`` (no inference)."""
    import json

    from treeinfer._io import atomic_write_json, atomic_write_text, staged_output_dir
    from treeinfer.plots import save_figure

    record = json.loads((out / "results.json").read_text())
    sugg_d = json.loads((out / "suggestions_seed0.json").read_text())
    conf = {k: tuple(v) if isinstance(v, list) else v for k, v in record["config"].items()}
    if "init" not in conf:  # a record of the first version: uniform start, constant Adam step
        conf.update(init="uniform", final_learning_rate=None, kT_velocity=False)
    cfg = DesignConfig(**conf)
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
            ("init", args.init),
            ("batch", args.batch),
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
    seeds, first_sugg = run_seeds(
        cfg, tree, sim, list(range(args.seed, args.seed + cfg.seeds)), args.quiet
    )
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
