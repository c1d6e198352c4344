"""The child process of ``benchmarks/time_to_posterior.py``: one timed path (``reference``,
``today``, ``fast`` or ``importance``) in a fresh Python process. The parent starts it as
``python -m benchmarks.time_to_posterior --child MODE --workdir DIR --result FILE ...``;
:func:`benchmarks.time_to_posterior.main` hands ``--child`` to :func:`child` here, which reads
``DIR/data.npz`` and writes its record (phase marks, stored particles, final particles) as JSON
to ``FILE``."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

N_STEPS, DT = 300, 0.01


def _write(result: str, record: dict) -> None:
    """The record as JSON, with the XLA programs this process compiled and those it loaded from
    the persistent cache (:mod:`treeinfer.sim.compile_stats`)."""
    from treeinfer.sim.compile_stats import compile_stats

    record["compile_stats"] = compile_stats().since()
    Path(result).write_text(json.dumps(record))


def child(args) -> int:
    import jax

    from treeinfer.sim.compile_stats import compile_stats

    compile_stats()  # listening from the start: every compilation of the path is counted
    from benchmarks.inference import EXAMPLES
    from treeinfer.data.trajectories import Trajectory
    from treeinfer.inference import infer, make_problem
    from treeinfer.tree import load_tree

    marks = {"imports": time.time()}
    data = np.load(Path(args.workdir) / "data.npz")
    tree = load_tree(EXAMPLES / "three_branch.yaml")
    t = np.arange(N_STEPS) * DT
    trajs = [
        Trajectory(t, f, tau, tau_dot, f"pull{i}")
        for i, (f, tau, tau_dot) in enumerate(
            zip(data["train_force"], data["train_tau"], data["train_tau_dot"])
        )
    ]
    problem = make_problem(tree, trajs, substeps=args.substeps, likelihood="boltzmann")
    marks["problem"] = time.time()
    mode = args.child
    record: dict = {"mode": mode}
    if mode == "importance":
        return child_importance(args, problem, marks, record)
    if mode == "reference_importance":
        return child_reference_importance(args, problem, marks, record)
    if mode == "fast":
        from treeinfer.inference.mapfit import (
            fit_problem,
            laplace_particles,
            problem_with_gradients,
        )

        fit = fit_problem(
            problem,
            "boltzmann",
            n_starts=args.starts,
            seed=0,
            jacobian=args.fast_jacobian,
            max_iterations=args.lm_iterations,
            agree=args.lm_agree,
        )
        theta0 = laplace_particles(
            jax.random.key(0),
            fit,
            args.particles,
            scale=args.laplace_scale,
            covariance=args.laplace_covariance,
        )
        marks["map_fit"] = time.time()
        record["map"] = {
            "theta": fit.theta.tolist(),
            "iterations": fit.iterations,
            "converged": fit.converged.tolist(),
            "values": fit.values.tolist(),
        }
        problem = problem_with_gradients(problem, args.fast_gradients)
        n_iter = args.fast_iterations
        options = (
            {} if args.fast_learning_rate is None else {"learning_rate": args.fast_learning_rate}
        )
    else:
        options = {}
        theta0 = None
        n_iter = args.reference_iterations if mode == "reference" else args.today_iterations
    checks: list = []

    def on_chunk(iteration, state):
        theta = np.asarray(jax.block_until_ready(state.position))
        checks.append({"iteration": int(iteration), "time": time.time(), "theta": theta.tolist()})

    if theta0 is not None:
        checks.append({"iteration": 0, "time": time.time(), "theta": np.asarray(theta0).tolist()})
    stop_when = None
    if mode == "fast" and args.stop_when_converged:
        from treeinfer.inference import ConvergenceCriterion

        stop_when = ConvergenceCriterion(
            min_iterations=args.min_iterations, window=args.check_every
        )
    if mode == "fast" and args.fast_warmup > 0:
        # Adam's first steps move every coordinate by ~lr whatever its gradient: from particles
        # already near the posterior that is a kick; the sampler ramps the learning rate up
        options["warmup"] = args.fast_warmup
    posterior = infer(
        problem,
        "nnsvgd",
        n_particles=args.particles,
        n_iterations=n_iter,
        seed=0,
        progress=False,
        initial_theta=theta0,
        callback=on_chunk,
        callback_every=args.check_every,
        trace_every=None,
        stop_when=stop_when,
        **options,
    )
    final_theta = np.asarray(posterior.theta)
    record["stop_reason"] = posterior.run.stop_reason
    record["n_iterations_done"] = int(posterior.run.settings["n_iterations_done"])
    marks["infer"] = time.time()
    record.update(
        {
            "marks": marks,
            "checks": checks,
            "n_iterations": n_iter,
            "gradient": problem.settings["gradient"],
            "final_theta": final_theta.tolist(),
        }
    )
    _write(args.result, record)
    return 0


def child_importance(args, problem, marks, record) -> int:
    """The ``importance`` path: :func:`treeinfer.inference.fast_posterior` (one rollout
    program: screened LM fit, PSIS importance sampling); when its own check fails (``ok``
    False: Pareto k_hat > 0.7 or too few effective samples) NNSVGD runs from its particles as
    in the ``fast`` path, stopped by the convergence criterion."""
    import jax

    from treeinfer.inference import fast_posterior, infer

    res = fast_posterior(
        problem,
        args.particles,
        n_starts=args.is_starts,
        seed=0,
        df=args.is_df,
        max_rounds=args.is_rounds,
    )
    marks["map_fit"] = time.time()
    record["importance"] = {k: v for k, v in res.settings.items()}
    record["importance"]["phases_s"] = res.phases
    record["map"] = {
        "theta": res.fit.theta.tolist(),
        "iterations": res.fit.iterations,
        "converged": res.fit.converged.tolist(),
        "values": res.fit.values.tolist(),
    }
    checks = [{"iteration": 0, "time": time.time(), "theta": res.theta.tolist()}]
    final_theta, n_done, reason = res.theta, 0, "importance_ok"
    if not res.ok:
        from treeinfer.inference import ConvergenceCriterion

        def on_chunk(iteration, state):
            theta = np.asarray(jax.block_until_ready(state.position))
            checks.append(
                {"iteration": int(iteration), "time": time.time(), "theta": theta.tolist()}
            )

        posterior = infer(
            problem,
            "nnsvgd",
            n_particles=args.particles,
            n_iterations=args.fast_iterations,
            seed=0,
            progress=False,
            initial_theta=res.theta,
            callback=on_chunk,
            callback_every=args.check_every,
            trace_every=None,
            stop_when=ConvergenceCriterion(
                min_iterations=args.min_iterations, window=args.check_every
            ),
            warmup=args.fast_warmup,
        )
        final_theta = np.asarray(posterior.theta)
        n_done = int(posterior.run.settings["n_iterations_done"])
        reason = f"importance failed ({res.reason}); nnsvgd: {posterior.run.stop_reason}"
    marks["infer"] = time.time()
    record.update(
        {
            "marks": marks,
            "checks": checks,
            "n_iterations": n_done,
            "n_iterations_done": n_done,
            "stop_reason": reason,
            "gradient": "none (importance sampling)" if res.ok else problem.settings["gradient"],
            "final_theta": np.asarray(final_theta).tolist(),
        }
    )
    _write(args.result, record)
    return 0


def child_reference_importance(args, problem, marks, record) -> int:
    """The ``--reference-kind importance`` reference: an importance posterior with many draws
    (4 adaptive rounds of 4096 Student-t draws, ``32 P`` particles, shuffled; the parent averages
    the band over the 32 ``P``-particle subsets, so the reference has the runs' KDE smoothing and
    about 1 % noise: 128 exact draws' bands scatter by 6.6 %). An exact sampler in the limit,
    unlike NNSVGD, whose 128 particles settle into a band 10-15 % narrower on this problem
    (``experiments/importance_robustness.py``, BENCHMARKS.md issue 15 fifth pass)."""
    from treeinfer.inference import fast_posterior

    n = 32 * args.particles
    res = fast_posterior(
        problem, n, n_starts=args.is_starts, n_draws=4096, seed=1234, max_rounds=4,
        target_ess=float("inf"), df=8.0,
    )  # fmt: skip
    theta = np.random.default_rng(0).permutation(res.theta)
    marks["infer"] = time.time()
    record["importance"] = dict(res.settings)
    record.update(
        {
            "marks": marks,
            "checks": [],
            "n_iterations": 0,
            "n_iterations_done": 0,
            "stop_reason": f"importance reference ({res.reason or 'ok'})",
            "gradient": "none (importance sampling)",
            "final_theta": np.asarray(theta).tolist(),
        }
    )
    _write(args.result, record)
    return 0
