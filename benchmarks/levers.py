"""Speed levers, each measured against the library's own simulator in one run.

    python -m benchmarks.levers                    # all levers, platform defaults
    python -m benchmarks.levers --only precision,loops --batch 64

* ``precision``: float32 (default), float32 with ``JAX_DEFAULT_MATMUL_PRECISION=highest`` (no
  TF32 matrix units on GPU) and float64 (``JAX_ENABLE_X64=1``), each in a fresh process, checked
  against MuJoCo C (``simulate_reference``, float64) on the three-branch example under the
  standard problem's three profiles, inside a batch of ``--batch`` parameter sets and alone;
  and their rollout times at that batch.
* ``loops``: ``benchmarks.variants.simulate_variant``: ``lax.scan`` unroll of the observation
  loop, full unroll of the substep loop, and MuJoCo's Euler integrator (implicit damping)
  instead of ``implicitfast``; compile and run time at ``--batch`` x 3 profiles, and the largest
  difference from ``simulate``.
* ``donation``: one jitted NNSVGD step of the standard problem with the state donated
  (``donate_argnums``) or not.
* ``profile``: one vmapped ``mjx.step`` of the example tree: kernel-launching ops in the
  optimised HLO, XLA's cost model (flops, bytes) and its wall time at several batch sizes;
* ``xla_flags``: the library's rollout at ``--batch`` under XLA GPU flag variants (command
  buffers / CUDA graphs off, and extended to while loops), each in a fresh process;
* ``cache``: the standard problem's ``make_problem`` + ``infer`` (``--cache-iterations``) in two
  fresh processes sharing an empty persistent compilation cache (cold, then warm).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks import _common as C
from benchmarks._levers_child import (  # noqa: F401 -- re-exported; the children import it
    _standard_inputs,
    precision_child,
    rollout_time_child,
)

ROOT = Path(__file__).resolve().parent.parent


PRECISION_VARIANTS = {
    "float32": {},
    "float32, matmul precision highest": {"JAX_DEFAULT_MATMUL_PRECISION": "highest"},
    "float64": {"JAX_ENABLE_X64": "1"},
}


def lever_precision(args) -> dict:
    out = {}
    for name, extra in PRECISION_VARIANTS.items():
        if time.perf_counter() - args.t_start > args.budget_s:
            out[name] = {"skipped": "budget"}
            continue
        env = {
            **os.environ,
            **extra,
            "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
        }
        code = (
            "import json; from benchmarks.levers import precision_child; "
            f"print(json.dumps(precision_child({args.batch}, {args.steps}, {args.n_check}, "
            f"{args.reps})))"
        )
        proc = subprocess.run(
            [sys.executable, "-c", code],
            env=env,
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=False,
        )
        if proc.returncode != 0:
            out[name] = {"error": proc.stderr[-2000:]}
            print(f"   {name}: failed: {proc.stderr.strip()[-300:]}", flush=True)
            continue
        v = out[name] = json.loads(proc.stdout.strip().splitlines()[-1])
        print(
            f"   {name:<34}: |tau - C| <= {v['max_abs_tau_error_m']:.2e} m, |tau_dot - C| <= "
            f"{v['max_abs_tau_dot_error_m_s']:.2e} m/s (max tau {v['max_abs_tau_m']:.3f} m), "
            f"batch {v['batch']} vs alone {v['max_abs_tau_diff_batch_vs_alone_m']:.1e} m; "
            f"{C.fmt_rate(v['steps_per_s'])} steps/s at N={v['batch']}x3, compile "
            f"{v['compile_s']:.1f} s",
            flush=True,
        )
    return out


def lever_loops(args) -> dict:
    import jax
    import jax.numpy as jnp

    from benchmarks.rollout import sample_gains
    from benchmarks.variants import simulate_variant, with_integrator
    from treeinfer.sim import make_simulator, simulate

    tree, forces, _, _ = _standard_inputs(args.steps)
    sim = make_simulator(tree, obs_dt=0.01, accuracy="coarse")
    kp, kd = sample_gains(tree, args.batch, seed=5)
    a, b, f = (jnp.asarray(x, jnp.float32) for x in (kp, kd, forces))
    steps = args.batch * forces.shape[0] * args.steps * sim.substeps
    # (name, simulator function of (sim, kp, kd, forces), simulator)
    variants = [("simulate (library)", simulate, sim)]
    for name, kw in [
        ("variant, defaults", {}),
        ("scan unroll=2", {"unroll_outer": 2}),
        ("scan unroll=5", {"unroll_outer": 5}),
        ("substeps unrolled", {"unroll_inner": True}),
    ]:
        variants.append((name, functools.partial(simulate_variant, **kw), sim))
    variants.append(
        (
            "mjx backend",
            simulate,
            make_simulator(tree, obs_dt=0.01, backend="mjx", accuracy="coarse"),
        )
    )
    variants.append(("mjx, euler integrator", simulate, with_integrator(sim, "euler")))
    rows, ref = [], None
    for name, sim_fn, s in variants:
        if time.perf_counter() - args.t_start > args.budget_s:
            rows.append({"variant": name, "skipped": "budget"})
            continue
        fn = jax.jit(functools.partial(sim_fn, s))
        t0 = time.perf_counter()
        compiled = fn.lower(a, b, f).compile()
        t_compile = time.perf_counter() - t0
        out = C.block(compiled(a, b, f))
        tau = np.asarray(out.tau)
        if ref is None:
            ref = tau
        tm = C.time_calls(functools.partial(compiled, a, b, f), reps=args.reps, min_time_s=1.0)
        row = {
            "variant": name,
            "compile_s": t_compile,
            "rollout_s": tm["median_s"],
            "steps_per_s": steps / tm["median_s"],
            "max_abs_diff_from_library_m": float(np.max(np.abs(tau - ref))),
            "all_stable": bool(np.all(np.asarray(out.stable))),
        }
        rows.append(row)
        print(
            f"   {name:<22} {C.fmt_rate(row['steps_per_s'])} steps/s ({tm['median_s'] * 1e3:.1f} "
            f"ms), compile {t_compile:.1f} s, max |diff| "
            f"{row['max_abs_diff_from_library_m']:.1e} m",
            flush=True,
        )
        del compiled, fn, out
        jax.clear_caches()
    return {
        "batch": args.batch,
        "n_profiles": forces.shape[0],
        "n_steps": args.steps,
        "substeps": sim.substeps,
        "rows": rows,
    }


def lever_donation(args) -> dict:
    from benchmarks.inference import make_standard_problem, step_time

    problem = make_standard_problem(n_steps=args.steps)[0]
    out = {}
    for donate in (False, True):
        r = step_time(problem, args.particles, args.reps, donate=donate)
        out["donated" if donate else "not_donated"] = r
        print(
            f"   donate={donate}: {r['step_ms']:.1f} ms/it (compile {r['compile_s']:.1f} s)",
            flush=True,
        )
    return out


def lever_cache(args) -> dict:
    out = {}
    with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
        for label in ("cold", "warm"):
            js = Path(tmp) / f"{label}.json"
            cmd = [
                sys.executable,
                "-m",
                "benchmarks.inference",
                "--no-scaling",
                "--particles",
                str(args.particles),
                "--iterations",
                str(args.cache_iterations),
                "--steps",
                str(args.steps),
                "--compile-cache",
                cache,
                "--out",
                str(js),
            ]
            t0 = time.perf_counter()
            proc = subprocess.run(
                cmd, env=env, cwd=ROOT, capture_output=True, text=True, check=False
            )
            wall = time.perf_counter() - t0
            if proc.returncode != 0:
                out[label] = {"error": proc.stderr[-2000:]}
                continue
            s = json.loads(js.read_text())["inference"]["standard"]
            out[label] = {
                "process_wall_s": wall,
                "make_problem_s": s["make_problem_s"],
                "infer_s": s["infer_s"],
                "time_to_posterior_s": s["time_to_posterior_s"],
                "compiles": s["compiles_total"],
                "cache_hits": s["compilation_cache_hits"],
                "iteration_ms": s["iteration_ms_steady"],
            }
            print(
                f"   {label}: make_problem + infer({args.cache_iterations} it) = "
                f"{s['time_to_posterior_s']:.1f} s (process {wall:.1f} s), compiles "
                f"{s['compiles_total']}, cache hits {s['compilation_cache_hits']}",
                flush=True,
            )
    return out


def _hlo_profile(compiled, n: int, reps: int) -> dict:
    """Kernel-launching ops, while loops, XLA's cost model and wall time of a compiled step."""
    import re

    hlo = compiled.as_text()
    kernels = len(
        re.findall(
            r"= \S+ (?:fusion|custom-call|convolution|dot|copy|transpose|reduce|scatter|gather)\(",
            hlo,
        )
    )
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    flops = float(cost.get("flops", float("nan"))) if cost else float("nan")
    nbytes = float(cost.get("bytes accessed", float("nan"))) if cost else float("nan")
    return {
        "kernels_in_hlo": kernels,
        "while_loops": hlo.count(" while("),
        "flops_per_step": flops,
        "bytes_per_step": nbytes,
        "bytes_per_particle_step": nbytes / n,
        "flops_per_particle_step": flops / n,
    }


def lever_profile(args) -> dict:
    """What one physics step of the 3-branch example costs on each backend (``mjx.step`` and the
    fused hinge-tree step): XLA kernels, cost-model flops and bytes, and wall time of a single
    vmapped step at several batch sizes."""
    import jax
    import jax.numpy as jnp

    from treeinfer.sim import fused as hd
    from treeinfer.sim import make_simulator
    from treeinfer.sim.mjx import import_mjx

    mjx = import_mjx()
    tree, _, _, _ = _standard_inputs(args.steps)
    sim = make_simulator(tree, obs_dt=0.01, accuracy="coarse")
    model, t, nv = sim.model, sim.hinge_tree, sim.mj_model.nv
    stiff = [float(x) for x in sim.mj_model.jnt_stiffness[sim.mj_model.dof_jntid]]
    damp = [float(x) for x in sim.mj_model.dof_damping]

    def fused_step(q, v, kp):
        out = hd.step(
            t,
            q,
            v,
            [kp] + stiff[1:],
            damp,
            [0.0] * nv,
            sim.sim_dt,
            sim.grasp_body,
            (0.5, 0.0, 0.0),
            (0.0, 0.0, -5.0),
            (0.1, 0.0, 0.0),
        )
        return out.qpos, out.qvel

    rows = []
    for n in args.profile_batches:
        data = jax.vmap(lambda _: mjx.make_data(model))(jnp.arange(n))
        q = jnp.zeros((n, nv)) + 0.1
        inputs = {
            "mjx.step": (jax.jit(jax.vmap(lambda d: mjx.step(model, d))), (data,)),
            "fused step": (jax.jit(jax.vmap(fused_step)), (q, q, jnp.full((n,), 50.0))),
        }
        for name, (fn, xs) in inputs.items():
            compiled = fn.lower(*xs).compile()
            row = {"backend_step": name, "batch": n, **_hlo_profile(compiled, n, args.reps)}
            C.block(compiled(*xs))
            tm = C.time_calls(functools.partial(compiled, *xs), reps=args.reps, min_time_s=0.5)
            row.update(
                step_us=1e6 * tm["median_s"],
                effective_GB_s=row["bytes_per_step"] / tm["median_s"] / 1e9,
            )
            rows.append(row)
            print(
                f"   N={n:>6} {name:<10}: {row['step_us']:.1f} us; {row['kernels_in_hlo']} "
                f"kernel ops in HLO, {row['while_loops']} while loops; cost model "
                f"{row['flops_per_particle_step']:.0f} flop and "
                f"{row['bytes_per_particle_step']:.0f} B per particle-step",
                flush=True,
            )
    return {"rows": rows, "nbody": sim.mj_model.nbody, "nv": nv}


XLA_FLAG_VARIANTS = {
    "default": "",
    "no command buffers": "--xla_gpu_enable_command_buffer=",
    "command buffers incl. while/conditional": (
        "--xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,WHILE,CONDITIONAL"
    ),
}


def lever_xla_flags(args) -> dict:
    out = {}
    for name, flags in XLA_FLAG_VARIANTS.items():
        if time.perf_counter() - args.t_start > args.budget_s:
            out[name] = {"skipped": "budget"}
            continue
        env = {
            **os.environ,
            "XLA_FLAGS": (os.environ.get("XLA_FLAGS", "") + " " + flags).strip(),
            "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
        }
        code = (
            f"import json; from benchmarks.levers import rollout_time_child; "
            f"print(json.dumps(rollout_time_child({args.batch}, {args.steps}, {args.reps})))"
        )
        proc = subprocess.run(
            [sys.executable, "-c", code],
            env=env,
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=False,
        )
        if proc.returncode == 0:
            r = json.loads(proc.stdout.strip().splitlines()[-1])
            out[name] = {"xla_flags": flags, **r}
            print(
                f"   {name:<40} {r['rollout_s'] * 1e3:.1f} ms at N={args.batch}x3 "
                f"({r['us_per_step']:.1f} us per step), compile {r['compile_s']:.1f} s",
                flush=True,
            )
        else:
            out[name] = {"xla_flags": flags, "error": proc.stderr[-1500:]}
            print(
                f"   {name:<40} failed: "
                f"{proc.stderr.strip().splitlines()[-1][:200] if proc.stderr.strip() else '?'}",
                flush=True,
            )
    return out


LEVERS = {
    "precision": lever_precision,
    "loops": lever_loops,
    "donation": lever_donation,
    "cache": lever_cache,
    "profile": lever_profile,
    "xla_flags": lever_xla_flags,
}


def main(argv=None) -> int:
    import jax

    on_gpu = jax.devices()[0].platform == "gpu"
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--only", default=",".join(LEVERS), help=f"comma list of {list(LEVERS)}")
    p.add_argument(
        "--batch",
        type=int,
        default=1664 if on_gpu else 16,
        help="parameter sets per rollout (1664 = one standard NNSVGD iteration's rows)",
    )
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--particles", type=int, default=128 if on_gpu else 8)
    p.add_argument("--n-check", type=int, default=4, help="parameter sets compared with C")
    p.add_argument("--cache-iterations", type=int, default=20)
    p.add_argument(
        "--profile-batches",
        type=lambda t: [int(x) for x in t.split(",")],
        default=[1, 4992, 131072] if on_gpu else [1, 64],
    )
    p.add_argument("--reps", type=int, default=5)
    p.add_argument("--budget-s", type=float, default=float("inf"))
    p.add_argument("--machine", default=None)
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    args.t_start = time.perf_counter()
    record = {
        "machine": C.machine_info(),
        "settings": {k: v for k, v in vars(args).items() if k != "t_start"},
    }
    print(f"machine: {record['machine']}", flush=True)
    out = args.out or (C.RESULTS_DIR / f"{args.machine or C.default_machine_name()}.json")
    for name in args.only.split(","):
        if time.perf_counter() - args.t_start > args.budget_s:
            record[name] = {"skipped": "budget"}
            continue
        print(f"lever: {name}", flush=True)
        record[name] = LEVERS[name](args)
        C.merge_results(out, "levers", record, {})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
