"""Rollout throughput of the batched MJX simulator against native MuJoCo, in one run.

    python -m benchmarks.rollout                       # defaults for the platform found
    python -m benchmarks.rollout --trees 3 --batches 1,64,1024 --steps 100

For 1-, 3- and 6-branch chains (every joint inferred) and each batch size N (parameter sets,
one force profile), three ways of doing the same rollouts:

* **MJX**: ``treeinfer.simulator.simulate`` jitted, N parameter sets x 1 profile in one call
  (static settle of every parameter set, then the pull);
* **mujoco.rollout**: MuJoCo's native multithreaded C rollout (``threads`` = host cores), one
  ``MjModel`` per rollout (that is how it takes per-particle stiffness/damping), started from
  the settled state (the settle is not timed for it: see ``settle_share``);
* **naive**: ``treeinfer.simulator.simulate_reference``, a Python loop of ``mujoco.mj_step``
  per particle (settle included), timed on a few particles (its rate does not depend on N).

Throughput is **particle-steps per second** = N * B * T * substeps / wall seconds, B = 1 force
profile, T observation steps, ``substeps`` simulation steps per observation (the physics steps
actually taken). MJX compile time is reported separately (lower = trace to StableHLO, compile =
XLA). The parameter sets are a pool of 64 log-uniform draws from the prior box, repeated
cyclically to fill N (so the C path needs only 64 settles); the cost per step does not depend
on the values.

The C rollout applies the pull through ``xfrc_applied`` of a massless-in-effect body (1e-6 kg)
welded to the grasped branch at the grasp point, so the world-frame force needs no lever-arm
torque and is a plain open-loop control; the script checks that its displacement matches
``simulate_reference`` (``check`` in the JSON) and that MJX matches too.
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import time

import numpy as np

from benchmarks import _common as C
from benchmarks._rollout_native import (  # noqa: F401 -- re-exported
    CRollout,
    c_controls,
    c_pool,
    rollout_model,
)

POOL = 64


def bench_tree(n_branches: int):
    """A chain of ``n_branches`` tapering branches, every joint inferred, default prior box."""
    from treeinfer.tree import chain

    return chain(
        n_branches,
        lengths=np.linspace(0.7, 0.4, n_branches).tolist() if n_branches > 1 else 0.7,
        radii=np.linspace(0.03, 0.012, n_branches).tolist() if n_branches > 1 else 0.03,
        angles_deg=[0.0] + [-10.0] * (n_branches - 1) if n_branches > 1 else 0.0,
        base_position=(0.0, 0.0, 1.5),
        base_pitch_deg=20.0,
        levels=n_branches,
        name=f"chain{n_branches}",
    )


def sample_gains(tree, n: int, seed: int = 0):
    """``n`` log-uniform draws from the prior box: kp [n, R], kd [n, R]."""
    lo, hi = tree.bounds_array()
    rng = np.random.default_rng(seed)
    theta = np.log(lo) + rng.uniform(size=(n, lo.size)) * (np.log(hi) - np.log(lo))
    r = tree.n_inferred
    return np.exp(theta[:, :r]), np.exp(theta[:, r:])


def pull_profile(n_steps: int, dt: float) -> np.ndarray:
    """[1, T] N: ramp to 8 N over the first half, hold."""
    from treeinfer.data import ramp_hold

    dur = n_steps * dt
    return ramp_hold(8.0, 0.5 * dur, 0.5 * dur - dt, dt, dur, dt)[None, :n_steps]


# ---- the benchmark -------------------------------------------------------------------------
def run_tree(n_branches, batches, n_steps, args, out_rows, record, save=lambda: None):
    import jax
    import jax.numpy as jnp

    from treeinfer.sim import make_simulator, settle, simulate
    from treeinfer.sim.reference import simulate_reference

    tree = bench_tree(n_branches)
    sim = make_simulator(tree, obs_dt=args.obs_dt, backend=args.backend, accuracy="coarse")
    forces = pull_profile(n_steps, sim.obs_dt)
    kp_pool, kd_pool = sample_gains(tree, POOL, seed=n_branches)
    steps_per_rollout = n_steps * sim.substeps
    info = {
        "n_branches": n_branches,
        "backend": sim.backend,
        "nq": sim.mj_model.nq,
        "nbody": sim.mj_model.nbody,
        "substeps": sim.substeps,
        "sim_dt": sim.sim_dt,
        "obs_dt": sim.obs_dt,
        "n_steps": n_steps,
        "steps_per_rollout": steps_per_rollout,
    }
    print(
        f"\n== {n_branches}-branch chain, {sim.backend} backend: nq={sim.mj_model.nq}, "
        f"substeps={sim.substeps}, T={n_steps} "
        f"({steps_per_rollout} physics steps per rollout)",
        flush=True,
    )

    # native C paths
    m, bid = rollout_model(tree, sim)
    t0 = time.perf_counter()
    models, states, c_rest = c_pool(sim, m, kp_pool, kd_pool)
    info["c_settle_s_per_particle_python"] = (time.perf_counter() - t0) / POOL
    crun = CRollout(sim, m, bid, models, states, forces, args.threads)
    tau_ref, _ = simulate_reference(sim, kp_pool[0], kd_pool[0], forces[0])
    tau_c = crun.tau(c_rest[0])
    # naive Python loop of mj_step: a few particles (rate does not depend on N)
    t0 = time.perf_counter()
    for i in range(args.naive_particles):
        simulate_reference(sim, kp_pool[i], kd_pool[i], forces[0])
    naive_s = (time.perf_counter() - t0) / args.naive_particles
    info["naive_s_per_particle"] = naive_s
    info["naive_steps_per_s"] = steps_per_rollout / naive_s
    info["naive_settle_s_per_particle"] = info["c_settle_s_per_particle_python"]
    info["naive_pull_steps_per_s"] = steps_per_rollout / max(
        naive_s - info["naive_settle_s_per_particle"], 1e-12
    )
    record.setdefault("trees", []).append(info)

    sim_fn = jax.jit(lambda a, b, f: simulate(sim, a, b, f))
    check = None
    for n in batches:
        if time.perf_counter() - args.t_start > args.budget_s:
            print(
                f"   budget of {args.budget_s:.0f} s spent: skipping batch {n} and larger",
                flush=True,
            )
            record.setdefault("skipped", []).append({"n_branches": n_branches, "batch": n})
            continue
        idx = np.arange(n) % POOL
        kp = jnp.asarray(kp_pool[idx], jnp.float32)
        kd = jnp.asarray(kd_pool[idx], jnp.float32)
        if args.shard and jax.device_count() > 1 and n % jax.device_count() == 0:
            from treeinfer.inference import shard_particles

            kp, kd = shard_particles(kp), shard_particles(kd)  # XLA splits the batch over devices
        fj = jnp.asarray(forces, jnp.float32)
        t0 = time.perf_counter()
        lowered = sim_fn.lower(kp, kd, fj)
        t1 = time.perf_counter()
        compiled = lowered.compile()
        t2 = time.perf_counter()
        out = C.block(compiled(kp, kd, fj))  # warm-up
        if check is None:
            tau_mjx = np.asarray(out.tau[0, 0])
            check = {
                "max_abs_mjx_minus_reference_m": float(np.max(np.abs(tau_mjx - tau_ref))),
                "max_abs_rollout_minus_reference_m": float(np.max(np.abs(tau_c - tau_ref))),
                "max_abs_tau_reference_m": float(np.max(np.abs(tau_ref))),
                "all_stable": bool(np.all(np.asarray(out.stable))),
            }
            info["check"] = check
            print(
                f"   check: |MJX - C ref| = {check['max_abs_mjx_minus_reference_m']:.2e} m, "
                f"|rollout - C ref| = {check['max_abs_rollout_minus_reference_m']:.2e} m "
                f"(max tau {check['max_abs_tau_reference_m']:.3f} m)",
                flush=True,
            )
        tm = C.time_calls(
            functools.partial(compiled, kp, kd, fj), reps=args.reps, min_time_s=args.min_time_s
        )
        mjx_rate = n * steps_per_rollout / tm["median_s"]
        row = {
            "n_branches": n_branches,
            "backend": sim.backend,
            "batch": n,
            "mjx_s": tm["median_s"],
            "mjx_steps_per_s": mjx_rate,
            "mjx_devices": len(kp.sharding.device_set),
            "lower_s": t1 - t0,
            "compile_s": t2 - t1,
            "mjx_reps": tm["reps"],
            "all_stable": bool(np.all(np.asarray(out.stable))),
        }
        del out
        n_c = min(n, args.c_max_batch)
        if n_c >= 1:
            crun.run(min(n_c, crun.chunk))  # warm-up
            tc = C.time_calls(
                functools.partial(crun.run, n_c), reps=args.reps, min_time_s=args.min_time_s
            )
            row.update(
                {
                    "c_batch": n_c,
                    "c_s": tc["median_s"],
                    "c_steps_per_s": n_c * steps_per_rollout / tc["median_s"],
                }
            )
            row["mjx_over_c"] = mjx_rate / row["c_steps_per_s"]
        row["naive_steps_per_s"] = info["naive_steps_per_s"]
        row["mjx_over_naive"] = mjx_rate / info["naive_steps_per_s"]
        out_rows.append(row)
        save()
        print(
            f"   N={n:>6}: MJX {C.fmt_rate(mjx_rate)} steps/s ({tm['median_s'] * 1e3:.1f} ms; "
            f"lower {t1 - t0:.1f} s, compile {t2 - t1:.1f} s) | "
            f"C rollout {C.fmt_rate(row.get('c_steps_per_s'))} (N={n_c}) | "
            f"naive {C.fmt_rate(info['naive_steps_per_s'])} | "
            f"MJX/C {row.get('mjx_over_c', float('nan')):.3g}",
            flush=True,
        )
        if args.breakdown and n == max(batches):
            # settle share: the static solve alone at the same batch
            st = jax.jit(lambda a, b: settle(sim, a, b))
            t0 = time.perf_counter()
            cs = st.lower(kp, kd).compile()
            tcs = time.perf_counter() - t0
            C.block(cs(kp, kd))
            ts = C.time_calls(
                functools.partial(cs, kp, kd), reps=args.reps, min_time_s=args.min_time_s
            )
            row["settle_s"] = ts["median_s"]
            row["settle_share"] = ts["median_s"] / tm["median_s"]
            row["settle_compile_s"] = tcs
            save()
            print(
                f"   settle alone at N={n}: {ts['median_s'] * 1e3:.1f} ms = "
                f"{row['settle_share']:.0%} of the rollout "
                f"(compile {tcs:.1f} s)",
                flush=True,
            )
        del compiled, lowered
        jax.clear_caches()
    crun.close()


def main(argv=None) -> int:
    import jax

    on_gpu = jax.devices()[0].platform == "gpu"
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--trees", default="1,3,6", help="branch counts of the chains")
    p.add_argument(
        "--backend",
        default="fused",
        choices=["fused", "mjx"],
        help="simulator backend (the mjx_* columns of the JSON hold its figures)",
    )
    p.add_argument(
        "--batches",
        default=None,
        help="batch sizes (parameter sets); default 1..131072 on GPU, 1..1024 on CPU",
    )
    p.add_argument("--steps", type=int, default=300, help="observation steps T per rollout")
    p.add_argument("--obs-dt", type=float, default=0.01, help="s between observations")
    p.add_argument("--threads", type=int, default=os.cpu_count(), help="mujoco.rollout threads")
    p.add_argument(
        "--c-max-batch",
        type=int,
        default=None,
        help="largest batch run through mujoco.rollout (its rate is flat in N); "
        "default 16384 GPU host, 1024 CPU",
    )
    p.add_argument("--naive-particles", type=int, default=2)
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--min-time-s", type=float, default=1.0)
    p.add_argument(
        "--no-breakdown",
        dest="breakdown",
        action="store_false",
        help="skip timing the settle alone at the largest batch",
    )
    p.add_argument(
        "--budget-s", type=float, default=float("inf"), help="stop starting new batches after this"
    )
    p.add_argument(
        "--compile-cache", default=None, help="persistent compilation cache dir (default: off)"
    )
    p.add_argument(
        "--shard",
        action="store_true",
        help="split the parameter sets over all JAX devices (e.g. CPU cores exposed with "
        "XLA_FLAGS=--xla_force_host_platform_device_count=N)",
    )
    p.add_argument(
        "--append",
        action="store_true",
        help="keep rows of other trees/batches already in the JSON (default: replace the section)",
    )
    p.add_argument(
        "--machine", default=None, help="name of the JSON file (default from the device)"
    )
    p.add_argument(
        "--out",
        default=None,
        help="JSON path (default experiments/results/benchmarks/<machine>.json)",
    )
    args = p.parse_args(argv)
    args.t_start = time.perf_counter()
    if args.compile_cache:
        import treeinfer

        treeinfer.enable_compilation_cache(args.compile_cache)
    if args.batches is None:
        args.batches = "1,16,256,4096,32768,131072" if on_gpu else "1,16,256,1024"
    if args.c_max_batch is None:
        args.c_max_batch = 16384 if on_gpu else 1024
    batches = [int(b) for b in args.batches.split(",")]
    trees = [int(t) for t in args.trees.split(",")]
    record = {
        "machine": C.machine_info(),
        "settings": {k: v for k, v in vars(args).items() if k != "t_start"},
        "definition": "particle-steps/s = N * B * T * substeps / s, B = 1 profile; "
        "MJX includes the settle, "
        "mujoco.rollout starts from settled states",
    }
    print(f"machine: {record['machine']}", flush=True)
    rows: list[dict] = []
    record["rows"] = rows
    machine = args.machine or C.default_machine_name()
    out = args.out or (C.RESULTS_DIR / f"{machine}.json")
    previous = C.read_section(out, "rollout") if args.append else {}

    def save():
        merged = {
            **record,
            "rows": _merge_rows(previous.get("rows", []), rows, ("n_branches", "backend", "batch")),
            "trees": _merge_rows(
                previous.get("trees", []), record.get("trees", []), ("n_branches", "backend")
            ),
        }
        C.merge_results(out, "rollout", merged, summary(merged["rows"]))

    for nb in trees:
        run_tree(nb, batches, args.steps, args, rows, record, save)
        save()
    print(
        "\nparticle-steps/s (N * T * substeps / s); MJX includes the settle; "
        "C rollout from settled states"
    )
    C.print_table(
        [
            {
                **r,
                "mjx": C.fmt_rate(r["mjx_steps_per_s"]),
                "c": C.fmt_rate(r.get("c_steps_per_s")),
                "naive": C.fmt_rate(r["naive_steps_per_s"]),
                "r_c": f"{r.get('mjx_over_c', float('nan')):.3g}",
                "r_n": f"{r['mjx_over_naive']:.3g}",
                "comp": f"{r['lower_s']:.0f}+{r['compile_s']:.0f}",
            }
            for r in rows
        ],
        [
            ("n_branches", "branches"),
            ("batch", "N"),
            ("mjx", "MJX"),
            ("c", "mujoco.rollout"),
            ("naive", "naive loop"),
            ("r_c", "MJX/rollout"),
            ("r_n", "MJX/naive"),
            ("comp", "lower+compile s"),
        ],
    )
    print(f"\nwrote {out}")
    return 0


def _merge_rows(old: list, new: list, keys: tuple) -> list:
    """``old`` rows not re-measured in ``new``, then ``new`` (rows matched on ``keys``; rows from
    before the fused backend existed are MJX rows)."""
    key = lambda r: tuple(r.get(k, "mjx" if k == "backend" else None) for k in keys)
    seen = {key(r) for r in new}
    return [r for r in old if key(r) not in seen] + list(new)


def summary(rows) -> dict:
    """Top-level keys: best MJX rate anywhere; MJX/rollout at the largest batch of the 3-branch
    chain (or the largest tree measured) where both ran."""
    if not rows:
        return {}
    best = max(rows, key=lambda r: r["mjx_steps_per_s"])
    both = [r for r in rows if "mjx_over_c" in r]
    ratio = None
    if both:
        pref = [r for r in both if r["n_branches"] == 3] or both
        pref = [r for r in pref if r.get("backend") == "fused"] or pref
        top = max(pref, key=lambda r: r["batch"])
        ratio = {
            "value": top["mjx_over_c"],
            "n_branches": top["n_branches"],
            "batch": top["batch"],
            "backend": top.get("backend", "mjx"),
            "c_batch": top["c_batch"],
        }
    return {
        "rollout_steps_per_s_max": best["mjx_steps_per_s"],
        "rollout_steps_per_s_max_at": {
            "n_branches": best["n_branches"],
            "batch": best["batch"],
            "backend": best.get("backend", "mjx"),
        },
        "mjx_over_mujoco_rollout_ratio": None if ratio is None else ratio["value"],
        "mjx_over_mujoco_rollout_ratio_at": ratio,
    }


if __name__ == "__main__":
    sys.exit(main())
