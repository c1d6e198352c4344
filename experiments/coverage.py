"""Calibration of the Gaussian measurement model on noisy sim-to-sim data (issue 11, targets).

For the built-in 2- and 3-branch examples: true gains (``default_true_params``), 5 training and
25 unseen test pulls simulated by plain MuJoCo (C, float64; an execution path independent of the
batched float32 simulator used for inference), then white noise on the recordings: ``2 mm`` on
displacement and ``2%`` of the largest peak force of the data set on force (one sensor, one
noise level for every pull; ``--force-noise``), velocity differentiated from the noisy
displacement, as for a recording. ``--likelihood ar1|student_t`` fits the other noise models.

Fit: ``likelihood_terms(kind="gaussian")`` (sigma_x inferred jointly, prior centred on the data
estimate) + the smoothed log box prior on the gains, sampled with numpyro's NUTS through the
finite-difference custom_jvp simulator (``treeinfer.model.finite_difference_jvp``), started
from the best of a few Adam maximisations. NUTS is used so the figures judge the LIKELIHOOD,
not a particle sampler's approximation.

Reported per tree:

* % of noisy unseen test points inside the 95% PREDICTIVE band (simulation + fitted noise,
  :func:`treeinfer.evaluation.metrics.noisy_predictive_interval`), and inside the parameter-only
  band; predictive NLL per point (:func:`treeinfer.evaluation.metrics.noisy_predictive_nll`). Test
  predictions are driven by the recorded (noisy) test forces, as they would be for a real recording.
* posterior std / Cramer-Rao bound per parameter, in log units: CRB from the simulator's
  sensitivities at the truth on the recorded training forces, ``Fisher = J^T J / sigma^2``
  (J by central differences, sigma = 2 mm, the displacement noise), which ignores the force
  noise (ratios above 1 expected with it), and the bound WITH the force noise,
  ``Fisher = sum_b J_b^T (C_b + sigma^2 I)^-1 J_b``, ``C_b`` of :mod:`treeinfer.model.force_noise`
  at the truth (the one to compare with under ``--noise-force``).
* with ``--noise-force``: ``force_noise_rms_mm``, sqrt(mean diag C) of the training pulls at
  the reference (2.3 mm for two_branch at full size; 0 would mean the term is not there), and
  the simulator backend.

``--check-force-noise`` runs no fit: :func:`force_noise_check` (point variance against Monte
Carlo, simulator mismatch, coverage at the truth with and without the term, both CRBs).

    python experiments/coverage.py --size cpu      # dt 20 ms, 2 s pulls (minutes on a CPU)
    python experiments/coverage.py --size full     # dt 10 ms, 3 s pulls (the issue's set-up)

Writes ``experiments/results/coverage[_full]/results.json`` and ``results.md``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

SIZES = {
    "tiny": {
        "dt": 0.02,
        "duration": 1.0,
        "n_train": 2,
        "n_test": 4,
        "warmup": 100,
        "samples": 100,
        "n_pred": 50,
    },
    "cpu": {
        "dt": 0.02,
        "duration": 2.0,
        "n_train": 5,
        "n_test": 25,
        "warmup": 300,
        "samples": 400,
        "n_pred": 200,
    },
    "full": {
        "dt": 0.01,
        "duration": 3.0,
        "n_train": 5,
        "n_test": 25,
        "warmup": 500,
        "samples": 1000,
        "n_pred": 400,
    },
}
SIGMA_X = 0.002  # m
FORCE_LEVEL = 0.02  # force noise std, share of the largest peak force of the data set


def make_case(
    tree_name: str, size: dict, seed: int, force_level: float = FORCE_LEVEL, with_clean=False
):
    """The benchmark case: ``(tree, sim, kp, kd, train, test, sigma_F)``, train/test noisy
    :class:`Trajectory` lists; ``with_clean``: the clean train and test pulls appended."""
    from treeinfer.data import from_spec, random_specs
    from treeinfer.data.trajectories import Trajectory, add_noise
    from treeinfer.examples import example_path
    from treeinfer.sim import make_simulator
    from treeinfer.sim.reference import simulate_reference
    from treeinfer.sim.synthetic import default_true_params
    from treeinfer.tree import load_tree

    tree = load_tree(example_path(tree_name))
    sim = make_simulator(tree, obs_dt=size["dt"])
    streams = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(4)]
    kp, kd = default_true_params(tree, streams[0])

    def clean_pulls(n, rng, tag):
        out = []
        for i, spec in enumerate(random_specs("mixed", n, size["duration"], (2.0, 8.0), rng)):
            f = from_spec(spec, size["duration"], size["dt"])
            tau, _ = simulate_reference(sim, kp, kd, f)
            out.append(Trajectory(np.arange(len(f)) * size["dt"], f, tau, None, f"{tag}{i}"))
        return out

    train = clean_pulls(size["n_train"], streams[1], "train")
    test = clean_pulls(size["n_test"], streams[2], "test")
    # one force sensor: the same noise std on every pull, 2% of the largest peak of the data set
    # (as experiments/common.noise_sigmas), not 2% of each pull's own peak
    sf = force_level * max(float(np.max(np.abs(t.force))) for t in train + test)

    def noisy(trajs):
        return [add_noise(t, sf, SIGMA_X, streams[3])._replace(source=t.source) for t in trajs]

    case = (tree, sim, kp, kd, noisy(train), noisy(test), sf)
    return case + (train, test) if with_clean else case


def fit(tree, sim, train, size: dict, seed: int, kind: str = "gaussian", noise_force=None):
    import jax
    import jax.numpy as jnp
    import optax
    from numpyro.infer import MCMC, NUTS

    from treeinfer.data import stack_trajectories
    from treeinfer.inference import box_prior
    from treeinfer.model import likelihood_terms

    obs = stack_trajectories(train)
    terms = likelihood_terms(sim, obs, kind, noise_force=noise_force)
    r = sim.n_joints
    box = box_prior(tree)
    lo, hi = np.log(tree.bounds_array()[0]), np.log(tree.bounds_array()[1])
    lower = np.concatenate([lo, terms.extra_lower])
    upper = np.concatenate([hi, terms.extra_upper])

    def logdensity(theta):  # [N, 2R + 1]
        return terms.log_likelihood(theta) + box(theta[:, : 2 * r]) + terms.extra_log_prior(theta)

    # best of 8 Adam maximisations from uniform draws in the box (batched: one simulator call)
    key = jax.random.key(seed)
    theta = jnp.asarray(
        lower + (upper - lower) * np.asarray(jax.random.uniform(key, (8, lower.size))), jnp.float32
    )
    opt = optax.adam(optax.cosine_decay_schedule(0.05, 400, 0.01))
    state = opt.init(theta)
    vg = jax.jit(
        jax.value_and_grad(
            lambda th: -jnp.sum(jnp.where(jnp.isfinite(v := logdensity(th)), v, -1e30))
        )
    )

    @jax.jit
    def adam_step(theta, state):
        _, g = vg(theta)
        g = jnp.where(jnp.isfinite(g), g, 0.0)
        upd, state = opt.update(g, state)
        return optax.apply_updates(theta, upd), state

    for _ in range(400):
        theta, state = adam_step(theta, state)
    lp = np.asarray(jax.jit(logdensity)(theta))
    start = theta[int(np.nanargmax(np.where(np.isfinite(lp), lp, -np.inf)))]

    def potential(th):
        v = logdensity(th[None])[0]
        return -jnp.where(jnp.isfinite(v), v, -1e30)

    mcmc = MCMC(
        NUTS(potential_fn=potential, target_accept_prob=0.85),
        num_warmup=size["warmup"],
        num_samples=size["samples"],
        progress_bar=False,
    )
    mcmc.run(jax.random.fold_in(key, 1), init_params=start)
    samples = np.asarray(mcmc.get_samples())
    div = int(np.sum(np.asarray(mcmc.get_extra_fields()["diverging"])))
    return terms, samples, float(np.max(lp)), div


def crb_log_std(sim, kp, kd, train, sigma_force=None) -> np.ndarray:
    """Cramer-Rao std per log parameter: Fisher = J^T J / sigma^2 over the training samples.

    With ``sigma_force`` (N) the bound of the errors-in-variables model instead: per pull
    ``Fisher_b = J_b^T (C_b + sigma^2 I)^-1 J_b``, ``C_b = sigma_F^2 J_F J_F^T`` at the truth
    (treeinfer.model.force_noise), i.e. the information left once the force noise is accounted
    for."""
    import jax.numpy as jnp

    from treeinfer.data import stack_trajectories
    from treeinfer.model import central_difference_jacobian
    from treeinfer.model.likelihood import gains_from_theta
    from treeinfer.sim import simulate

    obs = stack_trajectories(train)
    forces = jnp.asarray(obs.force, jnp.float32)
    r = sim.n_joints

    def tau(theta):
        k, d = gains_from_theta(theta, r)
        return simulate(sim, k, d, forces).tau

    theta = jnp.asarray(np.log(np.concatenate([kp, kd]))[None], jnp.float32)
    _, jac = central_difference_jacobian(tau, theta, rel_step=1e-2)
    mask = np.asarray(obs.mask, bool)
    if sigma_force is None:
        j = np.asarray(jac[0], float)[mask]  # [n, 2R]
        fisher = j.T @ j / SIGMA_X**2
        return np.sqrt(np.diag(np.linalg.inv(fisher)))
    from treeinfer.model import force_noise_basis

    theta_true = np.log(np.concatenate([kp, kd]))
    cov = force_noise_basis(sim, theta_true, obs.force, sigma_force, mask).covariance()
    fisher = 0.0
    for b in range(len(cov)):
        jb = np.asarray(jac[0, b], float)[mask[b]]  # [n_b, 2R]
        cb = cov[b][np.ix_(mask[b], mask[b])] + SIGMA_X**2 * np.eye(int(mask[b].sum()))
        fisher = fisher + jb.T @ np.linalg.solve(cb, jb)
    return np.sqrt(np.diag(np.linalg.inv(fisher)))


def force_noise_check(name: str, size: dict, seed: int, force_level: float, n_mc: int = 200):
    """Checks of the force-noise term on one case WITHOUT a fit (``--check-force-noise``; 1-4
    minutes per tree at full size on a CPU, most of it the reference MAP).

    At the true gains, on the case's own data (issue 11, the full-size R = 2 miss):

    * ``sim_mismatch_rms_mm``: RMS of MuJoCo C (``simulate_reference``, which made the data) minus
      the inference simulator on the clean training forces, per pull (model error, vs 2 mm);
    * ``force_rms_mm``: ``sqrt(mean diag C)`` of :func:`treeinfer.model.point_variance`
      per training pull, and ``mc_rms_mm_reference`` / ``mc_rms_mm_inference``: the same from
      the Monte-Carlo variance of ``n_mc`` rollouts of training pull 0 driven by its clean force
      plus white noise of std sigma_F, by MuJoCo C and by the inference simulator (no
      linearisation), with the median ratio of variances (MC / point_variance, t >= 20);
    * ``pct_inside_at_truth``: noisy test points inside ``tau(truth, recorded force) +- 1.96
      sqrt(sigma_x^2 [+ diag C])`` with sigma_x = 2 mm, without and with the term;
    * the Cramer-Rao std per log gain without and with the force noise (:func:`crb_log_std`);
    * ``pct_inside_at_truth_replicates``: the sampling spread of that figure for an EXACT model:
      the same 25 clean test forces with ``n_mc`` fresh draws of force and displacement noise
      (diag C of the clean forces): mean, sd and 2.5/97.5% quantiles of the pooled coverage.
      The force-induced error is slow, so one data set's 25 pulls hold few independent errors;
    * ``at_reference``: the errors-in-variables MAP that ``--noise-force auto`` linearises at
      (``likelihood_terms``), the sigma_x maximising the likelihood there (grid 1.5-3.5 mm), and
      the test coverage at that point with and without the term (what a fit should give).
    """
    import jax.numpy as jnp

    from treeinfer.data import stack_trajectories
    from treeinfer.model import force_noise as fn
    from treeinfer.model.likelihood import gains_from_theta, likelihood_terms
    from treeinfer.sim import simulate
    from treeinfer.sim.reference import simulate_reference

    tree, sim, kp, kd, train, test, sf, clean, clean_test = make_case(
        name, size, seed, force_level, with_clean=True
    )
    theta = np.log(np.concatenate([kp, kd]))

    def tau(forces, th=theta):  # [B, T] N -> [B, T] m at the log gains th [2R]
        k, d = gains_from_theta(jnp.asarray(th[None], sim.dtype), sim.n_joints)
        return np.asarray(simulate(sim, k, d, jnp.asarray(forces, sim.dtype)).tau[0], float)

    f_clean = np.stack([t.force for t in clean])
    ref = np.stack([simulate_reference(sim, kp, kd, f)[0] for f in f_clean])
    mismatch = np.sqrt(np.mean((ref - tau(f_clean)) ** 2, axis=1))
    obs = stack_trajectories(train)
    pv = fn.point_variance(fn.force_noise_basis(sim, theta, obs.force, sf))
    rng = np.random.default_rng(seed + 1)
    f0 = f_clean[0]
    noisy = f0 + sf * rng.standard_normal((n_mc, f0.size))
    mc_ref = np.var([simulate_reference(sim, kp, kd, f)[0] for f in noisy], axis=0)
    mc_inf = np.var(tau(noisy), axis=0)
    late = slice(20, None)
    test_obs = stack_trajectories(test)
    st = tau(test_obs.force)
    pv_test = fn.point_variance(fn.force_noise_basis(sim, theta, test_obs.force, sf))
    y = np.asarray(test_obs.displacement, float)
    z = 1.959963984540054

    def inside(var, pred):  # % of noisy test points in pred +- z sqrt(var)
        return 100.0 * float(np.mean(np.abs(y - pred) <= z * np.sqrt(var)))

    # the spread of the pooled coverage at the truth over fresh noise on the same test forces
    f_test = np.stack([t.force for t in clean_test])
    x_test = np.stack([t.displacement for t in clean_test])
    sd_test = np.sqrt(SIGMA_X**2 + fn.point_variance(fn.force_noise_basis(sim, theta, f_test, sf)))
    reps = []
    for _ in range(n_mc):
        pred = tau(f_test + sf * rng.standard_normal(f_test.shape))
        y_rep = x_test + SIGMA_X * rng.standard_normal(x_test.shape)
        reps.append(100.0 * float(np.mean(np.abs(y_rep - pred) <= z * sd_test)))
    reps = np.asarray(reps)
    replicates = {
        "n": n_mc,
        "mean": float(reps.mean()),
        "sd": float(reps.std()),
        "q025": float(np.quantile(reps, 0.025)),
        "q975": float(np.quantile(reps, 0.975)),
        "share_in_93_97": float(np.mean((reps >= 93.0) & (reps <= 97.0))),
    }
    # the reference point of --noise-force auto (the errors-in-variables MAP)
    terms = likelihood_terms(sim, obs, "gaussian", noise_force="auto")
    ref_theta = np.asarray(terms.force_noise.theta_ref, float)
    grid = np.log(np.linspace(0.0015, 0.0035, 41))
    th = np.column_stack([np.tile(ref_theta, (grid.size, 1)), grid])
    ll = np.asarray(terms.log_likelihood(jnp.asarray(th, sim.dtype)))
    sx = float(np.exp(grid[np.argmax(ll)]))
    st_ref = tau(test_obs.force, ref_theta)
    pv_ref = fn.point_variance(terms.force_noise.basis(sim, test_obs.force))
    at_ref = {
        "theta_ref": [float(v) for v in ref_theta],
        "theta_true": [float(v) for v in theta],
        "sigma_x_mm": 1e3 * sx,
        "pct_inside_sigma_x_only": inside(sx**2 + 0.0 * pv_ref, st_ref),
        "pct_inside_with_force_term": inside(sx**2 + pv_ref, st_ref),
    }
    return {
        "tree": name,
        "backend": sim.backend,
        "substeps": sim.substeps,
        "sigma_force_N": sf,
        "sim_mismatch_rms_mm": [1e3 * float(v) for v in mismatch],
        "force_rms_mm": [1e3 * float(v) for v in np.sqrt(pv.mean(axis=1))],
        "mc_rms_mm_reference": 1e3 * float(np.sqrt(mc_ref.mean())),
        "mc_rms_mm_inference": 1e3 * float(np.sqrt(mc_inf.mean())),
        "mc_over_point_variance_reference": float(np.median(mc_ref[late] / pv[0, late])),
        "mc_over_point_variance_inference": float(np.median(mc_inf[late] / pv[0, late])),
        "pct_inside_at_truth": {
            "sigma_x_only": inside(SIGMA_X**2 + 0.0 * pv_test, st),
            "with_force_term": inside(SIGMA_X**2 + pv_test, st),
        },
        "pct_inside_at_truth_replicates": replicates,
        "crb_log_std": [float(v) for v in crb_log_std(sim, kp, kd, train)],
        "crb_force_log_std": [float(v) for v in crb_log_std(sim, kp, kd, train, sf)],
        "at_reference": at_ref,
    }


def evaluate(
    sim, samples, test, n_pred: int, kind: str, sigma_x=None, level: float = 0.95, force_noise=None
) -> dict:
    import jax
    import jax.numpy as jnp

    from treeinfer.data import stack_trajectories
    from treeinfer.evaluation import metrics
    from treeinfer.model.likelihood import (
        gains_from_theta,
        noise_params_from_theta,
        predictive_noise_kind,
    )
    from treeinfer.sim import simulate

    obs = stack_trajectories(test)
    idx = np.linspace(0, len(samples) - 1, n_pred).astype(int)
    th = jnp.asarray(samples[idx], jnp.float32)
    k, d = gains_from_theta(th, sim.n_joints)
    ro = jax.jit(lambda k, d, f: simulate(sim, k, d, f))(k, d, jnp.asarray(obs.force, jnp.float32))
    valid = np.asarray(ro.stable).all(axis=1)
    sigma = noise_params_from_theta(th, sim.n_joints, sigma_x)
    band_kind = predictive_noise_kind(kind)
    # errors-in-variables: the test pulls are driven by their RECORDED (noisy) forces, so the
    # predictive band adds diag C of each test pull's own force (treeinfer.model.force_noise)
    extra = None
    if force_noise is not None:
        from treeinfer.model import point_variance

        extra = point_variance(force_noise.basis(sim, obs.force, np.asarray(obs.mask, bool)))
    bands = metrics.predictive_bands(ro.tau, sigma, level, valid, band_kind, extra_variance=extra)
    y, m = obs.displacement, obs.mask
    inside_pred = 1.0 - float(metrics.fraction_outside(*bands.predictive[:2], y, m))
    inside_par = 1.0 - float(metrics.fraction_outside(*bands.parameter[:2], y, m))
    nll = metrics.noisy_predictive_nll(ro.tau, y, sigma, m, valid, band_kind, extra_variance=extra)
    lo, hi = (np.asarray(v) for v in bands.predictive[:2])
    outside = np.asarray(metrics.outside(lo, hi, np.asarray(y)), bool) & np.asarray(m, bool)
    per_pull = 100.0 * (1.0 - outside.sum(1) / np.asarray(m, bool).sum(1))
    return {
        "pct_inside_predictive_band": 100 * inside_pred,
        "pct_inside_parameter_band": 100 * inside_par,
        "predictive_band_width_mm": 1e3 * float(metrics.ci_width(*bands.predictive[:2], m)),
        "parameter_band_width_mm": 1e3 * float(metrics.ci_width(*bands.parameter[:2], m)),
        "predictive_nll_per_point": float(nll.mean),
        "n_points": int(nll.n_points),
        "n_valid_draws": int(valid.sum()),
        "pct_inside_predictive_band_per_pull": [float(v) for v in per_pull],
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--size", choices=tuple(SIZES), default="cpu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--trees", default="two_branch,three_branch")
    p.add_argument("--out", default=None)
    p.add_argument("--likelihood", choices=("gaussian", "student_t", "ar1"), default="gaussian")
    p.add_argument(
        "--force-noise",
        type=float,
        default=FORCE_LEVEL,
        help="force noise std as a share of the largest peak force (default 0.02)",
    )
    p.add_argument(
        "--noise-force",
        default=None,
        help="model the force noise (errors in variables, gaussian only): newtons, 'P%%' of the "
        "largest recorded training force, 'auto' (estimated from the recorded force), or 'true' "
        "(the generator's value); default: not modelled",
    )
    p.add_argument(
        "--check-force-noise",
        action="store_true",
        help="no fit: check the force-noise term on the case at the true gains (Monte Carlo, "
        "simulator mismatch, coverage at the truth, CRB; force_noise_check) and write check.json",
    )
    args = p.parse_args(argv)
    import jax

    import treeinfer

    treeinfer.enable_compilation_cache()
    size = SIZES[args.size]
    out = (
        Path(args.out)
        if args.out
        else ROOT
        / "experiments"
        / "results"
        / "_".join(
            ["coverage"]
            + ([args.size] if args.size != "cpu" else [])
            + ([args.likelihood] if args.likelihood != "gaussian" else [])
            + ([f"force{args.force_noise:g}"] if args.force_noise != FORCE_LEVEL else [])
            + ([f"eiv-{args.noise_force.replace('%', 'pct')}"] if args.noise_force else [])
            + ([f"seed{args.seed}"] if args.seed else [])
        )
    )
    if args.check_force_noise:
        checks = {}
        for name in args.trees.split(","):
            t0 = time.time()
            c = force_noise_check(name, size, args.seed, args.force_noise)
            c["device"], c["seconds"] = str(jax.devices()[0]), time.time() - t0
            checks[name] = c
            print(json.dumps(c, indent=1), flush=True)
        out = out.with_name(out.name + "_check") if not args.out else out
        out.mkdir(parents=True, exist_ok=True)
        (out / "check.json").write_text(json.dumps(checks, indent=1))
        print(f"wrote {out}")
        return 0
    results = {
        "size": args.size,
        "settings": size,
        "sigma_x_m": SIGMA_X,
        "force_noise_share_of_largest_peak": args.force_noise,
        "likelihood": args.likelihood,
        "noise_force_option": args.noise_force,
        "seed": args.seed,
        "device": str(jax.devices()[0]),
        "trees": {},
    }
    for name in args.trees.split(","):
        t0 = time.time()
        tree, sim, kp, kd, train, test, sigma_f = make_case(name, size, args.seed, args.force_noise)
        nf = sigma_f if args.noise_force == "true" else args.noise_force
        terms, samples, best_lp, div = fit(
            tree, sim, train, size, args.seed, args.likelihood, noise_force=nf
        )
        force_rms = None  # sqrt(mean diag C) on the training pulls at theta_ref, mm
        if terms.force_noise is not None:
            from treeinfer.data import stack_trajectories
            from treeinfer.model import point_variance

            tobs = stack_trajectories(train)
            pv = point_variance(terms.force_noise.basis(sim, tobs.force, np.asarray(tobs.mask)))
            force_rms = 1e3 * float(np.sqrt(np.mean(pv[np.asarray(tobs.mask, bool)])))
        labels = list(tree.parameter_labels()) + list(terms.extra_labels)
        nominal = {"sigma_x": math.log(SIGMA_X)}  # the displacement noise (force noise excluded)
        truth = np.concatenate(
            [np.log(kp), np.log(kd), [nominal.get(lab, np.nan) for lab in terms.extra_labels]]
        )
        crb = crb_log_std(sim, kp, kd, train)
        crb_f = crb_log_std(sim, kp, kd, train, sigma_f) if sigma_f > 0 else crb
        std = samples.std(axis=0)
        q = np.quantile(samples, [0.025, 0.975], axis=0)

        def natural(i, x, labels=labels):
            return float(1 / (1 + np.exp(-x)) if labels[i] == "rho" else np.exp(x))

        params = {
            lab: {
                "truth": natural(i, truth[i]) if np.isfinite(truth[i]) else None,
                "posterior_mean": natural(i, samples[:, i].mean()),
                "log_std": float(std[i]),
                "crb_log_std": float(crb[i]) if i < len(crb) else None,
                "std_over_crb": float(std[i] / crb[i]) if i < len(crb) else None,
                "crb_force_log_std": float(crb_f[i]) if i < len(crb) else None,
                "std_over_crb_force": float(std[i] / crb_f[i]) if i < len(crb) else None,
                "truth_in_95": bool(q[0, i] <= truth[i] <= q[1, i])
                if np.isfinite(truth[i])
                else None,
            }
            for i, lab in enumerate(labels)
        }
        ev = evaluate(
            sim,
            samples,
            test,
            size["n_pred"],
            args.likelihood,
            terms.sigma_x,
            force_noise=terms.force_noise,
        )
        results["trees"][name] = {
            "parameters": params,
            "evaluation": ev,
            "noise_estimate_m": terms.settings["noise_estimate"],
            "sigma_force_N": sigma_f,
            "simulator_backend": sim.backend,
            "force_noise_rms_mm": force_rms,
            "noise_force_model": None
            if terms.force_noise is None
            else terms.force_noise.settings(),
            "nuts_divergences": div,
            "best_start_logdensity": best_lp,
            "seconds": time.time() - t0,
        }
        print(
            f"{name} ({args.likelihood}): {ev['pct_inside_predictive_band']:.1f}% inside the "
            f"95% predictive band "
            f"({ev['pct_inside_parameter_band']:.1f}% inside the parameter band), NLL "
            f"{ev['predictive_nll_per_point']:.3f} nats/point, median over test pulls "
            f"{np.median(ev['pct_inside_predictive_band_per_pull']):.1f}%, "
            f"{time.time() - t0:.0f} s"
            + (f"; {terms.force_noise.description}" if terms.force_noise is not None else "")
            + (f"; force-induced rms {force_rms:.2f} mm" if force_rms is not None else "")
            + f"; simulator backend {sim.backend}",
            flush=True,
        )
        for lab, v in params.items():
            print(
                f"  {lab:14s} truth {v['truth'] or float('nan'):.4g} "
                f"mean {v['posterior_mean']:.4g} "
                f"log-std {v['log_std']:.3g}"
                + (
                    f" CRB {v['crb_log_std']:.3g} ratio {v['std_over_crb']:.2f}"
                    f" (with force noise: CRB {v['crb_force_log_std']:.3g} "
                    f"ratio {v['std_over_crb_force']:.2f})"
                    if v["crb_log_std"]
                    else ""
                )
                + f" in95 {v['truth_in_95']}",
                flush=True,
            )
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=1))
    lines = [
        f"# Coverage and CRB ratio, size `{args.size}` ({args.likelihood} likelihood, NUTS)\n",
        (
            f"2 mm displacement + {100 * args.force_noise:g}% force noise (of the largest peak); "
            f"settings {json.dumps(size)}; seed {args.seed}; "
            f"device {results['device']}.\n"
        ),
        "| tree | % inside 95% predictive band | % inside parameter band | NLL / point |",
        "|---|---|---|---|",
    ]
    for name, rr in results["trees"].items():
        ev = rr["evaluation"]
        lines.append(
            f"| {name} | {ev['pct_inside_predictive_band']:.1f} "
            f"| {ev['pct_inside_parameter_band']:.1f} "
            f"| {ev['predictive_nll_per_point']:.3f} |"
        )
    lines += [
        "",
        (
            "| tree | parameter | truth | posterior mean | log std | CRB log std | std / CRB "
            "| CRB with force noise | std / that CRB | truth in 95% |"
        ),
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, rr in results["trees"].items():
        for lab, v in rr["parameters"].items():
            crb_s = f"{v['crb_log_std']:.3g}" if v["crb_log_std"] else "-"
            ratio = f"{v['std_over_crb']:.2f}" if v["std_over_crb"] else "-"
            crb_f = f"{v['crb_force_log_std']:.3g}" if v["crb_force_log_std"] else "-"
            ratio_f = f"{v['std_over_crb_force']:.2f}" if v["std_over_crb_force"] else "-"
            lines.append(
                f"| {name} | {lab} | {v['truth'] or float('nan'):.4g} | {v['posterior_mean']:.4g} "
                f"| {v['log_std']:.3g} "
                f"| {crb_s} | {ratio} | {crb_f} | {ratio_f} | {v['truth_in_95']} |"
            )
    (out / "results.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
