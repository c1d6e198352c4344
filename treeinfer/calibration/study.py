"""The tree SBC study: draw truths, simulate noisy data, run the batched sampler, rank."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict

import numpy as np

from ..errors import ConfigError
from .config import SBCConfig, _labels, draw_truths
from .figures import _crb_ratios, _predictive_coverage
from .programs import build_program
from .stats import SBCResult, summarize_sbc

SAMPLER_NOTES = {
    "smc": "adaptive tempered SMC from exact prior draws (N particles, ESS-targeted temperature "
    "ladder, systematic resampling, random-walk MH moves with the cloud's covariance), then MH "
    "steps at beta = 1; draws = L of the N final particles at random",
    "mh": "Adam ascent of P starts (box prior), then P random-walk MH chains from the best "
    "mode; warm-up in phases with the chains' ensemble covariance and a scale tuned to "
    "25% acceptance; draws = final chain states after mh_steps fixed-proposal steps",
    "svgd": "final SVGD particles as draws",
}


def _sampler_stats(info: dict) -> dict:
    """Mean and extremes of the per-data-set sampler diagnostics (JSON-ready)."""
    out = {}
    for k, v in info.items():
        if k.startswith(("smc_", "mh_")):
            v = np.asarray(v, float)
            out[f"{k}_mean"] = float(np.mean(v))
            out[f"{k}_min"] = float(np.min(v))
            out[f"{k}_max"] = float(np.max(v))
    if "smc_beta_reached" in info:
        out["smc_datasets_forced_to_beta_1"] = int(np.sum(np.asarray(info["smc_beta_reached"]) < 1))
    return out


def _simulate_truths(sim, truth, forces, r):
    """``tau [N, B, T]`` and ``stable [N]`` of each data set's truth under its forces."""
    import jax

    from ..model.likelihood import gains_from_theta
    from ..sim import simulate

    def one(th, f):
        kp, kd = gains_from_theta(th[None, : 2 * r], r)
        ro = simulate(sim, kp, kd, f)
        return ro.tau[0], jax.numpy.all(ro.stable[0])

    return jax.jit(jax.vmap(one))(truth, forces)


def run_tree_sbc(
    tree,
    config: SBCConfig,
    progress: Callable[[int, int], None] | None = None,
    log: Callable[[str], None] = lambda msg: None,
) -> SBCResult:
    """SBC of ``tree``'s posterior under ``config`` (see :class:`SBCConfig`).

    Steps: draw N truths from the prior (:func:`draw_truths`); draw fresh force profiles for each
    data set; simulate every truth (one batched call; a truth whose rollout is unstable is redrawn,
    i.e. the prior is restricted to stable parameters, as the likelihood is); add noise of the
    chosen model (numpyro's sampler, scale sigma_x); run the batched program over chunks of data
    sets; rank the truths among the P final draws. ``progress(done, total)`` after every chunk.
    Returns an :class:`SBCResult` whose ``info`` holds timings and sampler diagnostics.
    """
    import jax
    import jax.numpy as jnp

    from ..data.forces import profile_set
    from ..model import noise as _noise
    from ..sim import DEFAULT_MAX_SIM_DT, make_simulator
    from ..sim.synthetic import sim_tree

    config.check()
    rng = np.random.default_rng(config.seed)
    n, r = config.datasets, tree.n_inferred
    infer_sigma = config.noise_displacement is None
    labels = _labels(tree, infer_sigma)
    dim = len(labels)
    truth = draw_truths(tree, config, rng, n)
    forces = np.stack(
        [
            profile_set("mixed", config.n_traj, config.duration, config.dt, seed=rng)
            for _ in range(n)
        ]
    )
    # one simulator for all data sets, stable up to the stiffest drawn truth
    kp_max = np.max(np.exp(truth[:, :r]), axis=0)
    sim = make_simulator(
        sim_tree(tree, kp_max),
        obs_dt=config.dt,
        max_sim_dt=config.max_sim_dt or DEFAULT_MAX_SIM_DT,
        backend=config.backend,
    )
    t0 = time.perf_counter()
    tau, stable = _simulate_truths(sim, jnp.asarray(truth), jnp.asarray(forces), r)
    # np.array, not asarray: device arrays come back read-only and the redraws write into them
    tau, stable = np.array(tau), np.array(stable)
    n_redrawn = 0
    for _ in range(20):  # redraw the (rare) unstable truths
        bad = np.flatnonzero(~stable)
        if bad.size == 0:
            break
        n_redrawn += bad.size
        truth[bad] = draw_truths(tree, config, rng, bad.size)
        # the simulator's step was chosen for kp_max: keep redraws below it
        truth[bad, :r] = np.minimum(truth[bad, :r], np.log(kp_max))
        t2, s2 = _simulate_truths(sim, jnp.asarray(truth[bad]), jnp.asarray(forces[bad]), r)
        tau[bad], stable[bad] = np.asarray(t2), np.asarray(s2)
    if not np.all(stable):
        raise ConfigError(
            "calibrate: prior draws keep giving unstable simulations; lower "
            "--max-sim-dt or narrow the prior box"
        )
    sigma = np.exp(truth[:, 2 * r]) if infer_sigma else np.full(n, float(config.noise_displacement))
    key = jax.random.key(config.seed)
    unit = _noise.noise_distribution(config.likelihood, 1.0, float(config.student_t_df))
    e = np.asarray(unit.sample(jax.random.fold_in(key, 1), tau.shape))
    x_obs = tau + sigma[:, None, None] * e
    forces_rec = _record_forces(forces, config.noise_force, rng)
    test = None
    if config.test_traj:
        f_test = np.stack(
            [
                profile_set("mixed", config.test_traj, config.duration, config.dt, seed=rng)
                for _ in range(n)
            ]
        )
        tau_t, st_t = _simulate_truths(sim, jnp.asarray(truth), jnp.asarray(f_test), r)
        e_t = np.asarray(unit.sample(jax.random.fold_in(key, 3), tau_t.shape))
        x_test = np.asarray(tau_t) + sigma[:, None, None] * e_t
        test = (_record_forces(f_test, config.noise_force, rng), x_test, np.asarray(st_t))
    t_sim = time.perf_counter() - t0

    p = config.particles
    if config.sampler == "smc":  # exact prior draws: the SMC target at beta = 0
        n0 = config.smc_particles
        theta0 = draw_truths(tree, config, rng, n * n0).reshape(n, n0, dim)
    else:  # uniform in the log box; log sigma_x uniform within +-1 of the centre
        lo, hi = np.log(tree.bounds_array()[0]), np.log(tree.bounds_array()[1])
        if infer_sigma:
            c = math.log(config.noise_prior_center)
            lo, hi = np.append(lo, c - 1.0), np.append(hi, c + 1.0)
        theta0 = lo + rng.uniform(size=(n, p, dim)) * (hi - lo)
    program = build_program(sim, tree, config, dim)
    keys = jax.random.split(jax.random.fold_in(key, 2), n)
    draws = np.empty((n, p, dim))
    infos: list[dict] = []
    t1 = time.perf_counter()
    t_first = None
    for start in range(0, n, config.chunk):
        sl = slice(start, min(n, start + config.chunk))
        m = sl.stop - sl.start
        pad = config.chunk - m  # keep one compiled shape: pad the last chunk by repetition
        idx = np.r_[np.arange(sl.start, sl.stop), np.full(pad, sl.start, int)]
        out, info = program(
            keys[idx],
            jnp.asarray(theta0[idx]),
            jnp.asarray(forces_rec[idx]),
            jnp.asarray(x_obs[idx]),
        )
        draws[sl] = np.asarray(out)[:m]
        infos.append({k: np.asarray(v)[:m] for k, v in info.items()})
        if t_first is None:
            t_first = time.perf_counter() - t1
        if progress is not None:
            progress(sl.stop, n)
    t_inf = time.perf_counter() - t1
    info = {k: np.concatenate([d[k] for d in infos]) for k in infos[0]}
    bad_draws = ~np.all(np.isfinite(draws), axis=(1, 2))
    if np.any(bad_draws):
        log(
            f"warning: {int(bad_draws.sum())} data sets gave non-finite draws; they are ranked "
            "with their finite draws replaced by the data set's median"
        )
        for i in np.flatnonzero(bad_draws):
            med = np.nanmedian(np.where(np.isfinite(draws[i]), draws[i], np.nan), axis=0)
            draws[i] = np.where(np.isfinite(draws[i]), draws[i], med)
    extra = _crb_ratios(sim, truth, draws, forces_rec, labels, config)
    if test is not None:
        extra.update(_predictive_coverage(sim, draws, test, config, infer_sigma))
    summary_info = {
        **extra,
        "sampler": config.sampler,
        "sampler_note": SAMPLER_NOTES[config.sampler],
        "n_redrawn_unstable_truths": int(n_redrawn),
        "n_nonfinite_final": int(np.sum(info["n_nonfinite"])),
        **_sampler_stats(info),
        "seconds_simulate_data": t_sim,
        "seconds_inference": t_inf,
        "seconds_first_chunk_incl_compile": t_first,
        "backend": sim.backend,
        "sim_dt": sim.sim_dt,
        "jax_backend": jax.default_backend(),
        "truth_units": "theta: natural log of Kp (N m/rad), Kd (N m s/rad), sigma_x (m)",
    }
    return summarize_sbc(truth, draws, labels, seed=config.seed, info=summary_info)


def _record_forces(forces, share: float, rng: np.random.Generator) -> np.ndarray:
    """Recorded forces: ``forces [N, B, T]`` plus white noise of std ``share`` times each data
    set's peak |force| (one sensor, one level per data set)."""
    if share <= 0:
        return forces
    peak = np.max(np.abs(forces), axis=(1, 2), keepdims=True)
    return forces + share * peak * rng.normal(size=forces.shape)


def config_record(tree_path, config: SBCConfig) -> dict:
    """``config.json`` content: every option, the seed and versions."""
    from ..io.provenance import versions

    return {
        "command": "calibrate",
        "tree": str(tree_path),
        "options": asdict(config),
        "versions": versions(extended=True),
    }
