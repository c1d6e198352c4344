"""Inference benchmark: the standard problem end to end, and how cost grows with R, P and T.

    python -m benchmarks.inference                              # GPU defaults
    python -m benchmarks.inference --particles 8 --iterations 2 --no-scaling   # a CPU taste

**Standard problem**: the built-in three-branch example (R = 3 inferred joints, D = 6), 128
particles, 3 training trajectories of 300 steps (dt = 0.01 s, ground truth from the C reference
``simulate_reference`` at the documented default true parameters), central differences, NNSVGD
(``treeinfer.infer(problem, "nnsvgd", ...)``). One iteration evaluates the simulator once on
P * (2D + 1) = 1664 parameter sets x 3 trajectories.

Reported:

* ``time_to_posterior_s``: a fresh ``make_problem`` + ``infer`` of ``--iterations`` (200)
  iterations in this process, compilation included (the inequality network is loaded from
  ``$TREEINFER_CACHE`` or trained, timed separately);
* ``nnsvgd_iteration_ms``: steady state, from the wall time between the ends of the driver's
  jitted chunks (``callback``), so no extra compile or run is needed;
* simulator calls per iteration (``simulate`` wrapped with a Python counter: calls traced into
  one ``step``) and the rows per call; XLA compilations during the run and during the
  steady-state chunks (``jax.monitoring`` events);
* peak host memory (``getrusage``) and device memory (``memory_stats``; GPU only);
* convergence: posterior mean of theta against the truth, and the change of the mean
  log-density over the last tenth of the run.

**Scaling** (``--scale-r``, ``--scale-p``, ``--scale-t``): time of one jitted NNSVGD ``step``
(one FD gradient of P particles + Stein update), median of ``--reps`` calls after compiling;
R uses chains of R branches (``benchmarks.rollout.bench_tree``).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks import _common as C

EXAMPLES = Path(__file__).resolve().parent.parent / "treeinfer" / "examples"


class SimulateCounter:
    """Wraps ``treeinfer.model.boltzmann.simulate`` (what the Boltzmann likelihood calls) with a
    Python counter: every call is one trace of the simulator into a jitted program; ``rows``
    records P of each."""

    def __init__(self):
        import treeinfer.model.boltzmann as lik

        self._lik = lik
        self._orig = lik.simulate
        self.calls = 0
        self.rows: list[int] = []

        def counted(sim, kp, kd, forces, grasp_fraction=None):
            self.calls += 1
            self.rows.append(int(np.shape(kp)[0]) * int(np.shape(forces)[0]))
            return self._orig(sim, kp, kd, forces, grasp_fraction)

        lik.simulate = counted

    def restore(self):
        self._lik.simulate = self._orig


class UnrolledSimulate:
    """Makes the likelihood's ``simulate`` unroll its loops (``unroll_outer`` observations per
    scan iteration, ``unroll_inner`` substeps per loop iteration; ``True``: all substeps), to
    measure loop overhead on the GPU without changing the library's defaults."""

    def __init__(self, unroll_outer: int = 1, unroll_inner=1):
        import treeinfer.model.boltzmann as lik

        self._lik, self._orig = lik, lik.simulate

        def unrolled(sim, kp, kd, forces, grasp_fraction=None):
            return self._orig(sim, kp, kd, forces, grasp_fraction, unroll_outer, unroll_inner)

        if unroll_outer != 1 or unroll_inner != 1:
            lik.simulate = unrolled

    def restore(self):
        self._lik.simulate = self._orig


def make_standard_problem(
    tree=None,
    n_traj: int = 3,
    n_steps: int = 300,
    dt: float = 0.01,
    seed: int = 0,
    backend: str = "fused",
    accurate: bool = False,
):
    """(problem, theta_true [D]) for ``tree`` (default: the built-in three-branch example).

    ``accurate``: the issue-12 accuracy-controlled step (``make_simulator(forces=...)``, the
    run layer's default) instead of the stability step (fewest stable substeps)."""
    from treeinfer.data import profile_set
    from treeinfer.data.trajectories import Trajectory
    from treeinfer.inference import make_problem
    from treeinfer.sim import make_simulator
    from treeinfer.sim.reference import simulate_reference
    from treeinfer.sim.synthetic import default_true_params
    from treeinfer.tree import load_tree

    tree = load_tree(EXAMPLES / "three_branch.yaml") if tree is None else tree
    kp, kd = default_true_params(tree, np.random.default_rng(seed))
    forces = profile_set("mixed", n=n_traj, duration=n_steps * dt, dt=dt, seed=seed)[:, :n_steps]
    sim = make_simulator(tree, obs_dt=dt, backend=backend, forces=forces if accurate else None)
    t = np.arange(n_steps) * dt
    trajs = []
    for i, f in enumerate(forces):
        tau, tau_dot = simulate_reference(sim, kp, kd, f)
        trajs.append(Trajectory(t, f, tau, tau_dot, f"pull{i}"))
    problem = make_problem(tree, trajs, sim=sim, likelihood="boltzmann")
    return problem, np.concatenate([np.log(kp), np.log(kd)])


def standard(args) -> dict:
    """Time to posterior, steady iteration time, calls/compiles per iteration, memory."""
    import jax

    from treeinfer.inference import infer

    counter = SimulateCounter()
    compiles = C.CompileCounter()
    out: dict = {"n_particles": args.particles, "n_iterations": args.iterations}
    try:
        with compiles:
            t0 = time.perf_counter()
            problem, theta_true = make_standard_problem(
                n_steps=args.steps, backend=args.backend, accurate=args.accurate
            )
            t_problem = time.perf_counter() - t0
            d = problem.dim
            marks: list[tuple[int, float, int]] = []

            def on_chunk(it, state):
                jax.block_until_ready(state.position)
                marks.append((it, time.perf_counter(), compiles.n))

            t1 = time.perf_counter()
            posterior = infer(
                problem,
                "nnsvgd",
                n_particles=args.particles,
                n_iterations=args.iterations,
                seed=0,
                progress=False,
                callback=on_chunk,
                callback_every=args.chunk,
            )
            t_infer = time.perf_counter() - t1
    finally:
        counter.restore()
    n_sim_traces = counter.calls
    steady = [
        (
            marks[i][0] - marks[i - 1][0],
            marks[i][1] - marks[i - 1][1],
            marks[i][2] - marks[i - 1][2],
        )
        for i in range(1, len(marks))
    ]
    it_s = sum(s[1] for s in steady) / max(1, sum(s[0] for s in steady)) if steady else float("nan")
    first_chunk_s = marks[0][1] - t1 if marks else float("nan")
    rows = P_rows = args.particles * (2 * d + 1)
    out.update(
        {
            "backend": problem.sim.backend,
            "dim": d,
            "substeps": problem.sim.substeps,
            "n_steps": args.steps,
            "rows_per_iteration": rows,
            "simulator_rows_per_call": sorted(set(counter.rows)),
            "particle_steps_per_iteration": P_rows * 3 * args.steps * problem.sim.substeps,
            "make_problem_s": t_problem,
            "infer_s": t_infer,
            "time_to_posterior_s": t_problem + t_infer,
            "first_chunk_s_incl_compile": first_chunk_s,
            "iteration_ms_steady": 1e3 * it_s,
            "steady_iterations_timed": sum(s[0] for s in steady),
            "compiles_total": compiles.n,
            "compile_seconds_total": compiles.seconds,
            "compiles_during_steady_chunks": sum(s[2] for s in steady),
            "compilation_cache_hits": compiles.cache_hits,
            "simulate_traces_total": n_sim_traces,
            "peak_host_mb": C.peak_host_mb(),
            "device_memory": C.device_memory_mb(),
        }
    )
    # simulator calls per iteration: trace one step abstractly and count simulate calls in it

    algorithm = problem.sampler("nnsvgd")
    counter = SimulateCounter()
    try:
        state = jax.eval_shape(
            algorithm.init, jax.random.key(0), jax.ShapeDtypeStruct((args.particles, d), np.float32)
        )
        counter.calls = 0
        jax.eval_shape(algorithm.step, jax.random.key(0), state)
        out["simulator_calls_per_iteration"] = counter.calls
    finally:
        counter.restore()
    # convergence: posterior mean vs truth, and the late log-density trend
    theta = np.asarray(posterior.theta)
    ok = np.isfinite(posterior.log_density)
    mean = theta[ok].mean(axis=0) if ok.any() else np.full(d, np.nan)
    ml = np.asarray(posterior.run.diagnostics.get("mean_logdensity", []))
    tail = max(1, len(ml) // 10)
    out.update(
        {
            "theta_true": theta_true,
            "posterior_mean_theta": mean,
            "posterior_sd_theta": theta[ok].std(axis=0) if ok.any() else np.full(d, np.nan),
            "abs_error_of_mean_log_units": np.abs(mean - theta_true),
            "finite_particles": int(ok.sum()),
            "mean_logdensity_last": float(ml[-1]) if len(ml) else None,
            "mean_logdensity_change_last_tenth": float(ml[-1] - ml[-1 - tail])
            if len(ml) > tail
            else None,
        }
    )
    print(
        f"standard problem ({problem.sim.backend} backend, R=3, P={args.particles}, "
        f"3 x {args.steps} steps, substeps {problem.sim.substeps}): "
        f"make_problem {t_problem:.1f} s, infer {t_infer:.1f} s ({args.iterations} it), "
        f"steady {1e3 * it_s:.1f} ms/it, compiles {compiles.n} "
        f"(steady chunks: {out['compiles_during_steady_chunks']}), "
        f"simulate calls/it {out['simulator_calls_per_iteration']} "
        f"on {out['simulator_rows_per_call']} rows, "
        f"host peak {out['peak_host_mb']:.0f} MB, device {out['device_memory']}",
        flush=True,
    )
    print(
        "   |posterior mean - truth| (log units): "
        f"{np.round(out['abs_error_of_mean_log_units'], 3).tolist()}, "
        f"sd {np.round(out['posterior_sd_theta'], 3).tolist()}",
        flush=True,
    )
    return out


def step_state(problem, n_particles: int, mesh=None, method: str = "shard_map"):
    """(algorithm, state) for timing NNSVGD steps: the state ``init`` would give, except log p and
    grad zero (they only feed the first direction), so no separate compile of ``init`` is needed.
    With ``mesh``, the particle axis is sharded over it (``treeinfer.inference.sharding``)."""
    import jax
    import jax.numpy as jnp

    from treeinfer.inference import initial_particles

    if mesh is not None:
        from treeinfer.inference import sharding

        problem = sharding.shard_problem(problem, mesh, method)
    algorithm = problem.sampler("nnsvgd")
    theta0 = initial_particles(problem, n_particles, seed=0)
    shapes = jax.eval_shape(algorithm.init, jax.random.key(0), theta0)
    state = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)._replace(position=theta0)
    if mesh is not None:
        from jax.sharding import NamedSharding
        from jax.sharding import PartitionSpec as P

        split, whole = sharding.particle_sharding(mesh), NamedSharding(mesh, P())
        state = jax.tree.map(
            lambda x: jax.device_put(x, split if x.ndim and x.shape[0] == n_particles else whole),
            state,
        )
    return algorithm, state


def step_time(
    problem,
    n_particles: int,
    reps: int,
    donate: bool = False,
    min_time_s: float = 0.5,
    mesh=None,
    n_final: int = 0,
    method: str = "shard_map",
) -> dict:
    """Compile time and median wall time of one jitted NNSVGD step for ``n_particles``
    (sharded over ``mesh`` if given); ``n_final`` > 0 also returns the positions after that
    many further steps from the same start (for comparing sharded and unsharded runs)."""
    import jax

    algorithm, state0 = step_state(problem, n_particles, mesh, method)
    step = jax.jit(algorithm.step, donate_argnums=(1,) if donate else ())
    key = jax.random.key(1)
    t0 = time.perf_counter()
    compiled = step.lower(key, state0).compile()
    t_compile = time.perf_counter() - t0
    out = {}
    if n_final:
        s = state0
        for _ in range(n_final):
            s, _ = compiled(key, s)
        out["final_positions"] = np.asarray(s.position)
    state, _ = C.block(compiled(key, state0))
    times = []
    t_start = time.perf_counter()
    while len(times) < reps or time.perf_counter() - t_start < min_time_s:
        t = time.perf_counter()
        state, info = C.block(compiled(key, state))
        times.append(time.perf_counter() - t)
        if len(times) >= 50:
            break
    return {
        "compile_s": t_compile,
        "step_ms": 1e3 * float(np.median(times)),
        "reps": len(times),
        "n_nonfinite": int(info.n_nonfinite),
        **out,
    }


def scaling(args) -> dict:
    from benchmarks.rollout import bench_tree

    out = {"R": [], "P": [], "T": []}

    def over_budget():
        return time.perf_counter() - args.t_start > args.budget_s

    std_problem = None
    for p in args.scale_p:
        if over_budget():
            break
        std_problem = (
            std_problem or make_standard_problem(n_steps=args.steps, backend=args.backend)[0]
        )
        r = step_time(std_problem, p, args.reps)
        out["P"].append({"n_particles": p, **r, "rows": p * (2 * std_problem.dim + 1)})
        print(f"   P={p:>5}: {r['step_ms']:.1f} ms/it (compile {r['compile_s']:.1f} s)", flush=True)
    for n in args.scale_r:
        if over_budget():
            break
        prob = make_standard_problem(tree=bench_tree(n), n_steps=args.steps, backend=args.backend)[
            0
        ]
        r = step_time(prob, args.particles, args.reps)
        out["R"].append(
            {
                "R": n,
                "substeps": prob.sim.substeps,
                **r,
                "rows": args.particles * (2 * prob.dim + 1),
            }
        )
        print(
            f"   R={n} (chain, substeps {prob.sim.substeps}): {r['step_ms']:.1f} ms/it "
            f"(compile {r['compile_s']:.1f} s)",
            flush=True,
        )
    for t in args.scale_t:
        if over_budget():
            break
        prob = make_standard_problem(n_steps=t, backend=args.backend)[0]
        r = step_time(prob, args.particles, args.reps)
        out["T"].append({"n_steps": t, **r})
        print(f"   T={t:>5}: {r['step_ms']:.1f} ms/it (compile {r['compile_s']:.1f} s)", flush=True)
    return out


def main(argv=None) -> int:
    import jax

    on_gpu = jax.devices()[0].platform == "gpu"
    ints = lambda s: [int(x) for x in s.split(",") if x]
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--particles", type=int, default=128)
    p.add_argument(
        "--backend", default="fused", choices=["fused", "mjx", "pallas"], help="simulator backend"
    )
    p.add_argument("--block", type=int, default=None, help="pallas backend: rollouts per kernel")
    p.add_argument("--iterations", type=int, default=200)
    p.add_argument("--chunk", type=int, default=None, help="driver chunk (default: iterations / 2)")
    p.add_argument("--steps", type=int, default=300, help="trajectory length T (observation steps)")
    p.add_argument("--no-standard", dest="standard", action="store_false")
    p.add_argument("--no-scaling", dest="scaling", action="store_false")
    p.add_argument("--scale-r", type=ints, default=[1, 3, 6] if on_gpu else [])
    p.add_argument("--scale-p", type=ints, default=[32, 512, 4096] if on_gpu else [])
    p.add_argument("--scale-t", type=ints, default=[100, 1000] if on_gpu else [])
    p.add_argument("--reps", type=int, default=5)
    p.add_argument("--budget-s", type=float, default=float("inf"))
    p.add_argument(
        "--compile-cache", default=None, help="persistent compilation cache dir (default: off)"
    )
    p.add_argument("--machine", default=None)
    p.add_argument("--out", default=None)
    p.add_argument(
        "--accurate",
        action="store_true",
        help="accuracy-controlled step (the run layer's default) instead of the stability step",
    )
    p.add_argument("--unroll-outer", type=int, default=1, help="observations per scan iteration")
    p.add_argument(
        "--unroll-inner",
        type=lambda v: True if v == "full" else int(v),
        default=1,
        help="substeps per loop iteration ('full': all)",
    )
    p.add_argument(
        "--step-only",
        action="store_true",
        help="only time one jitted NNSVGD step of the standard problem; print a STEP json line",
    )
    args = p.parse_args(argv)
    args.t_start = time.perf_counter()
    args.chunk = args.chunk or max(1, args.iterations // 2)
    if args.compile_cache:
        import treeinfer

        treeinfer.enable_compilation_cache(args.compile_cache)
    record = {
        "machine": C.machine_info(),
        "settings": {k: v for k, v in vars(args).items() if k != "t_start"},
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
    }
    unroll = UnrolledSimulate(args.unroll_outer, args.unroll_inner)
    if args.block:
        import treeinfer.sim.pallas

        treeinfer.sim.pallas.DEFAULT_BLOCK = args.block
    if args.step_only:
        import json

        problem = make_standard_problem(
            n_steps=args.steps, backend=args.backend, accurate=args.accurate
        )[0]
        r = step_time(problem, args.particles, args.reps)
        r.update(
            substeps=problem.sim.substeps,
            step_method=problem.sim.step_info.get("method"),
            backend=problem.sim.backend,
            xla_flags=record["xla_flags"],
            unroll_outer=args.unroll_outer,
            unroll_inner=args.unroll_inner,
            block=args.block,
        )
        print("STEP " + json.dumps(r), flush=True)
        unroll.restore()
        return 0
    print(f"machine: {record['machine']}", flush=True)
    machine = args.machine or C.default_machine_name()
    out = args.out or (C.RESULTS_DIR / f"{machine}.json")
    summary = {}
    if args.standard:
        s = standard(args)
        record["standard"] = s
        summary = {
            "nnsvgd_iteration_ms": s["iteration_ms_steady"],
            "time_to_posterior_s": s["time_to_posterior_s"],
            "standard_problem_particles": args.particles,
            "standard_problem_iterations": args.iterations,
        }
        C.merge_results(out, "inference", record, summary)
    if args.scaling and (args.scale_r or args.scale_p or args.scale_t):
        print("scaling (one jitted NNSVGD step):", flush=True)
        record["scaling"] = scaling(args)
        C.merge_results(out, "inference", record, summary)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
