"""Cost of one likelihood gradient, in rollouts per particle: central differences vs forward mode.

    python -m benchmarks.gradient_cost                 # standard problem, CPU or GPU found
    python -m benchmarks.gradient_cost --reverse       # also reverse mode (long compile)

On the standard problem (three-branch example, R = 3, D = 6, 3 pulls x 300 steps, P = 128
particles) it times, interleaved in one process so machine load hits all alike:

* ``rollout``: the batched log-likelihood of P particles (one rollout each): the unit;
* ``fd``: :func:`treeinfer.model.central_difference`, P x (2D + 1) rollouts in one call;
* ``jvp``: :func:`treeinfer.model.jvp_value_and_grad`, D tangents pushed through one
  primal rollout (exact);
* ``reverse`` (``--reverse``): :func:`treeinfer.model.autodiff_value_and_grad`;
* ``jvp_plain`` (``--plain-jvp``): ``jvp`` with the fused pull's sensitivity rule off
  (``treeinfer.sim.fused_backend.SENSITIVITY_RULE``): ``jax.jvp`` through the step code, the
  path before the rule;
* ``jvp_<layout>`` (``--backend pallas --layout A B ...``): ``jvp`` with the kernel's tangents
  in each further layout (``treeinfer.sim.pallas.TANGENT_LAYOUTS``: ``rows``, ``lanes``,
  ``sensitivity``); ``jvp`` itself takes the first (default: ``pallas.TANGENT_LAYOUT``, which
  ``TREEINFER_PALLAS_TANGENT_LAYOUT`` sets), so one process compares them:

      python -m benchmarks.gradient_cost --backend pallas --layout rows sensitivity lanes

Each is reported as steady wall time (minimum over ``--reps``), compile time, and
**rollout-equivalents per particle** = time / time(rollout). Central differences cost 2D + 1 = 13
by construction; the issue's target for the exact gradient is at most half of that. Results go
to ``experiments/results/benchmarks/<machine>.json`` under ``gradient_cost``.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from benchmarks import _common as C


def standard_likelihood(n_steps: int = 300, backend: str = "fused"):
    """(log-likelihood ``theta [N, 6] -> [N]``, theta_true [6]) of the standard problem, without
    the NN prior (it is not part of the gradient being timed)."""
    from benchmarks.inference import EXAMPLES
    from treeinfer.data import profile_set
    from treeinfer.data.trajectories import Trajectory, stack_trajectories
    from treeinfer.model import DEFAULT_KT, boltzmann_log_likelihood
    from treeinfer.sim import make_simulator
    from treeinfer.sim.reference import simulate_reference
    from treeinfer.sim.synthetic import default_true_params
    from treeinfer.tree import load_tree

    tree = load_tree(EXAMPLES / "three_branch.yaml")
    sim = make_simulator(tree, obs_dt=0.01, backend=backend, accuracy="coarse")
    kp, kd = default_true_params(tree, np.random.default_rng(0))
    forces = profile_set("mixed", n=3, duration=n_steps * 0.01, dt=0.01, seed=0)[:, :n_steps]
    t = np.arange(n_steps) * 0.01
    trajs = [
        Trajectory(t, f, *simulate_reference(sim, kp, kd, f), f"pull{i}")
        for i, f in enumerate(forces)
    ]
    loglik = boltzmann_log_likelihood(sim, stack_trajectories(trajs), DEFAULT_KT)
    return loglik, np.concatenate([np.log(kp), np.log(kd)])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--particles", type=int, default=128)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--reverse", action="store_true", help="also time reverse mode")
    p.add_argument(
        "--plain-jvp", action="store_true", help="also time jvp without the sensitivity rule"
    )
    p.add_argument("--backend", default="fused", choices=["fused", "pallas"])
    p.add_argument(
        "--layout",
        "--tangent-layout",
        dest="layout",
        nargs="+",
        default=None,
        choices=["rows", "lanes", "sensitivity"],
        help="pallas backend: how tangents share the kernel (treeinfer.sim.pallas; default its "
        "TANGENT_LAYOUT); several: jvp takes the first, jvp_<layout> each other",
    )
    p.add_argument("--machine", default=None)
    p.add_argument("--no-write", dest="write", action="store_false")
    args = p.parse_args(argv)
    if args.layout and args.backend != "pallas":
        p.error("--layout is for --backend pallas")

    import jax
    import jax.numpy as jnp

    import treeinfer.sim.pallas as pk
    from treeinfer.model import autodiff_value_and_grad, central_difference, jvp_value_and_grad

    # the kernel's tangent layout per jvp entry, set before each is traced (read at trace time)
    layouts = list(dict.fromkeys(args.layout or [pk.TANGENT_LAYOUT]))
    default_layout = pk.TANGENT_LAYOUT
    layout_of = {}
    if args.backend == "pallas":
        layout_of = {"jvp": layouts[0], "jvp_plain": layouts[0]}
        layout_of.update({f"jvp_{x}": x for x in layouts[1:]})
    info = C.machine_info()
    loglik, truth = standard_likelihood(args.steps, args.backend)
    rng = np.random.default_rng(1)
    theta = jnp.asarray(truth + 0.3 * rng.normal(size=(args.particles, truth.size)), jnp.float32)
    fns = {
        "rollout": jax.jit(loglik),
        "fd": jax.jit(central_difference(loglik)),
        "jvp": jax.jit(jvp_value_and_grad(loglik)),
    }
    if args.reverse:
        fns["reverse"] = jax.jit(autodiff_value_and_grad(loglik))
    for name in layout_of:
        if name.startswith("jvp_") and name != "jvp_plain":
            fns[name] = jax.jit(jvp_value_and_grad(loglik))
    if args.plain_jvp:
        fns["jvp_plain"] = jax.jit(jvp_value_and_grad(loglik))
    import treeinfer.sim.fused_backend as fb

    compile_s, out = {}, {}
    for name, fn in list(fns.items()):
        # compiled ahead of time, each from a fresh trace: the switches are read while tracing,
        # and the simulator's inner jit would otherwise reuse the first trace
        fb.SENSITIVITY_RULE = name != "jvp_plain"
        pk.TANGENT_LAYOUT = layout_of.get(name, default_layout)
        jax.clear_caches()
        t0 = time.perf_counter()
        fns[name] = fn.lower(theta).compile()
        out[name] = C.block(fns[name](theta))
        compile_s[name] = time.perf_counter() - t0
    fb.SENSITIVITY_RULE = True
    pk.TANGENT_LAYOUT = default_layout
    times = {name: [] for name in fns}
    for _ in range(args.reps):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            C.block(fn(theta))
            times[name].append(time.perf_counter() - t0)
    unit = min(times["rollout"])
    rows, results = [], {}
    g_fd = np.asarray(out["fd"][1])
    for name in fns:
        steady = min(times[name])
        rec = {
            "steady_s": steady,
            "first_call_s": compile_s[name],
            "rollouts_per_particle": steady / unit,
        }
        if name != "rollout":
            g = np.asarray(out[name][1])
            rec["max_abs_diff_vs_fd"] = float(np.abs(g - g_fd).max())
        if name in layout_of:
            rec["tangent_layout"] = layout_of[name]
            if name != "jvp":  # exact gradients of two layouts: equal to float32 rounding
                rec["max_abs_diff_vs_jvp"] = float(np.abs(g - np.asarray(out["jvp"][1])).max())
        results[name] = rec
        rows.append(
            {
                "name": name,
                "layout": layout_of.get(name, ""),
                "steady": f"{steady * 1e3:.1f} ms",
                "first": f"{compile_s[name]:.1f} s",
                "rollouts": f"{steady / unit:.1f}",
            }
        )
    C.print_table(
        rows,
        [("name", "gradient")]
        + ([("layout", "layout")] if layout_of else [])
        + [
            ("steady", "steady"),
            ("first", "compile+first"),
            ("rollouts", "rollouts/particle"),
        ],
    )
    for name in fns:
        if name not in ("rollout", "fd"):
            rel = results[name]["max_abs_diff_vs_fd"] / float(np.abs(g_fd).max())
            print(f"{name}: max |grad - fd grad| / max |fd grad| = {rel:.1e}")
            if "max_abs_diff_vs_jvp" in results[name]:
                rel = results[name]["max_abs_diff_vs_jvp"] / float(np.abs(g_fd).max())
                print(f"{name}: max |grad - jvp grad| / max |fd grad| = {rel:.1e}")
    d = truth.size
    ratio = results["jvp"]["steady_s"] / results["fd"]["steady_s"]
    label = f" [{layout_of['jvp']}]" if layout_of else ""
    print(f"jvp{label} / fd time: {ratio:.2f} (target <= 0.5; fd = 2D + 1 = {2 * d + 1} rollouts)")
    by_layout = {}
    for name, layout in layout_of.items():
        if name in results and name != "jvp_plain":
            by_layout[layout] = results[name]["steady_s"] / results["fd"]["steady_s"]
            if name != "jvp":
                print(f"{name} [{layout}] / fd time: {by_layout[layout]:.2f}")
    if "jvp_plain" in results:
        plain = results["jvp_plain"]["steady_s"] / results["fd"]["steady_s"]
        results["jvp_plain_over_fd"] = plain
        print(f"jvp without the sensitivity rule / fd time: {plain:.2f}")
    if "reverse" in results:
        rev = results["reverse"]["steady_s"] / results["fd"]["steady_s"]
        results["reverse_over_fd"] = rev
        print(f"reverse / fd time: {rev:.2f}")
    results.update(
        {
            "n_particles": args.particles,
            "n_steps": args.steps,
            "dim": d,
            "jvp_over_fd": ratio,
            "backend": args.backend,
            "tangent_layout": layout_of.get("jvp"),
            "jvp_over_fd_by_layout": by_layout,
            "machine": info,
        }
    )
    if args.write:
        path = C.RESULTS_DIR / f"{args.machine or C.default_machine_name()}.json"
        section = "gradient_cost" if args.backend == "fused" else f"gradient_cost_{args.backend}"
        C.merge_results(path, section, results, {})
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
