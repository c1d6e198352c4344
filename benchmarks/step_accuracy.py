"""The step/accuracy/throughput trade-off of the simulator's defaults, in one run.

    JAX_PLATFORMS=cpu python -m benchmarks.step_accuracy [--particles 256] [--reps 3]

On the standard problem's simulator (built-in three-branch example, three 3 s pulls from
``forces.profile_set("mixed", seed 0)`` at 10 ms), two configurations:

* **before**: zero-order hold of the forces, the stability step only (the old defaults);
* **after**: first-order hold and the accuracy-controlled step at the default tolerance
  (0.1 mm) on those profiles (``make_simulator(..., forces=...)``);
* **hold_at_after_step**: zero-order hold at the "after" step (isolates the cost per step).

For each: substeps, the step-doubling error estimate on the prior box
(:func:`treeinfer.sim.accuracy.choose_substeps_for_accuracy`), the time to choose the step, and
the rollout throughput of ``simulate`` jitted on N parameter sets (log-uniform in the prior box)
x 3 profiles (median of interleaved repetitions): observation-steps per second
(N * 3 * 300 / wall s, what inference pays per iteration) and physics particle-steps per second
(x substeps). The ratio of the two
configurations' observation-step rates is the throughput cost of the new defaults.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def main(argv=None) -> dict:
    import jax
    import jax.numpy as jnp

    from treeinfer.data import profile_set
    from treeinfer.examples import example_path
    from treeinfer.sim import make_simulator, simulate
    from treeinfer.sim.accuracy import choose_substeps_for_accuracy
    from treeinfer.tree import load_tree

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=256)
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args(argv)

    tree = load_tree(example_path("three_branch"))
    dt, n_steps = 0.01, 300
    forces = profile_set("mixed", n=3, duration=n_steps * dt, dt=dt, seed=0)[:, :n_steps]
    lo, hi = tree.bounds_array()
    rng = np.random.default_rng(0)
    theta = np.exp(rng.uniform(np.log(lo), np.log(hi), size=(args.particles, lo.size)))
    r = tree.n_inferred
    kp, kd = jnp.asarray(theta[:, :r], jnp.float32), jnp.asarray(theta[:, r:], jnp.float32)
    f = jnp.asarray(forces, jnp.float32)
    out = {"particles": args.particles, "profiles": 3, "steps": n_steps, "obs_dt": dt}
    built = {}
    for name, kwargs in (
        ("before", {"force_interp": "hold", "accuracy": "coarse"}),
        ("after", {"forces": forces}),
    ):
        t0 = time.perf_counter()
        built[name] = (make_simulator(tree, obs_dt=dt, **kwargs), time.perf_counter() - t0)
    # the per-step cost of the first-order hold: zero-order hold at the "after" step
    built["hold_at_after_step"] = (
        make_simulator(tree, obs_dt=dt, force_interp="hold", substeps=built["after"][0].substeps),
        0.0,
    )
    runs = {}
    for name, (sim, _) in built.items():
        runs[name] = jax.jit(lambda a, b, s=sim: simulate(s, a, b, f).tau)
        runs[name](kp, kd).block_until_ready()
    times = {name: [] for name in runs}
    for _ in range(args.reps):  # interleaved, so that a busy machine slows every config alike
        for name, run in runs.items():
            t0 = time.perf_counter()
            run(kp, kd).block_until_ready()
            times[name].append(time.perf_counter() - t0)
    for name, (sim, t_make) in built.items():
        if name == "after":
            est = sim.step_info["estimated_error"]
        else:
            _, est = choose_substeps_for_accuracy(sim, forces, 1.0)  # 1 m: just the estimate
        wall = float(np.median(times[name]))
        obs_rate = args.particles * 3 * n_steps / wall
        out[name] = {
            "force_interp": sim.force_interp,
            "substeps": sim.substeps,
            "sim_dt_s": sim.sim_dt,
            "estimated_error_m": est,
            "make_simulator_s": round(t_make, 2),
            "rollout_s_median": wall,
            "observation_steps_per_s": obs_rate,
            "particle_steps_per_s": obs_rate * sim.substeps,
        }
        print(name, json.dumps(out[name]), flush=True)
    out["throughput_ratio_after_over_before"] = (
        out["after"]["observation_steps_per_s"] / out["before"]["observation_steps_per_s"]
    )
    print("throughput ratio (after / before):", round(out["throughput_ratio_after_over_before"], 3))
    return out


if __name__ == "__main__":
    main()
