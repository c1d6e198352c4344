"""Data, posteriors and references of the design study (``experiments/design_study.py``): the
noisy pulls, every arm's posterior through the batched programs of
:mod:`treeinfer.inference.batch`, the held-out band and the Cramér-Rao reference."""

from __future__ import annotations

import time

import numpy as np

from experiments._design_config import DesignConfig, _say
from experiments._design_summary import CONDITIONS
from experiments.common import reference_trajectory


def _pull(sim, kp, kd, cand, cfg: DesignConfig, rng, name: str):
    """A noisy recording of candidate ``cand`` (ground truth from MuJoCo C)."""
    from treeinfer.data import add_noise
    from treeinfer.design import candidate_forces

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
    from treeinfer.model.likelihood import signal_omega2, suggest_kT

    sigma = cfg.noise_mm * 1e-3
    omega2 = signal_omega2(obs, sigma) if cfg.kT_velocity else 0.0
    return suggest_kT(sigma, int(np.shape(obs.displacement)[-1]), cfg.dt, omega2)


def _starts(tree, sim, kts, obs, grasp, seeds, cfg: DesignConfig, programs) -> list[np.ndarray]:
    """``[P, D]`` starting particles of each posterior (see the module docstring): Laplace draws
    around a MAP fit of each data set (:func:`treeinfer.inference.map_fits`: mapfit's
    Levenberg-Marquardt fit, all data sets in one compiled program), or uniform in the box."""
    import jax

    from treeinfer.inference import initial_particles, make_problem, map_fits
    from treeinfer.inference.mapfit import laplace_particles

    if cfg.init == "uniform":
        problem = make_problem(
            tree, obs[0], kT=1.0, sim=sim, nn_prior=False, likelihood="boltzmann"
        )
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
            cache=programs,
        )
        for fit, s in zip(fits, seeds[part]):
            key = jax.random.fold_in(jax.random.key(int(s)), 0x1A9)
            draws = laplace_particles(key, fit, cfg.n_particles, scale=cfg.laplace_scale)
            out.append(np.asarray(draws))
    return out


def _posteriors(tree, sim, jobs: list, cfg: DesignConfig, programs) -> list[_Post]:
    """Posteriors of ``jobs`` = [(trajectories, grasp fractions, seed)], all with the same
    number of pulls, through one batched NNSVGD program (``cfg.batch`` data sets per call);
    ``programs``: the study's :class:`treeinfer.sim.program_cache.ProgramCache`."""
    from treeinfer.data import stack_trajectories
    from treeinfer.inference import posterior_program, run_posteriors

    program = posterior_program(
        tree,
        sim,
        cfg.n_iterations,
        learning_rate=cfg.learning_rate,
        final_learning_rate=cfg.final_learning_rate,
        cache=programs,
    )
    obs = [stack_trajectories(trajs) for trajs, _, _ in jobs]
    kts = [_kT(o, cfg) for o in obs]
    grasp = [g for _, g, _ in jobs]
    seeds = [s for _, _, s in jobs]
    theta0 = _starts(tree, sim, kts, obs, grasp, seeds, cfg, programs)
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
    from treeinfer.evaluation.metrics import predictive_interval
    from treeinfer.inference.problem import predict

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


def run_seeds(cfg: DesignConfig, tree, sim, seeds: list[int], quiet: bool, programs=None):
    """The study for ``seeds``: returns ``(per-seed records, suggestions of the first seed)``.
    ``programs``: the :class:`treeinfer.sim.program_cache.ProgramCache` of the batched MAP and
    sampler programs, shared by both stages (and by later calls); None: one for this call."""
    from treeinfer.design import (
        Candidate,
        Target,
        candidate_forces,
        candidate_grid,
        score_candidates,
    )
    from treeinfer.sim.program_cache import ProgramCache
    from treeinfer.sim.synthetic import default_true_params

    programs = ProgramCache() if programs is None else programs

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
    post1 = _posteriors(tree, sim, [([data[s][3]], [1.0], s) for s in seeds], cfg, programs)
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
    post2 = _posteriors(tree, sim, [j[3] for j in jobs], cfg, programs)
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
