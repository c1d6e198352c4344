"""(a) Baselines (paper Fig. 3): NNSVGD against SVGD, SGHMC, SGLD and Metropolis-Hastings.

All samplers run on the same sim-to-sim problem (3-branch tree, R = 3, at the cpu and full
sizes) with the same particle count and iteration count. The baselines use the smoothed box
prior alone; NNSVGD adds the learned inequality prior (parent at least as stiff and as damped as
its child). Gradients are central finite differences through the simulator for every gradient
method; SGLD and SGHMC use Adam with a small learning rate for the drift (the paper's set-up).

Outputs in ``experiments/results/baselines/``: ``bands.png`` (95% predictive bands of test
trajectories, one row per sampler, ground truth in red), ``metrics.png`` (CI width, % GT outside,
predictive NLL), ``pairs.png`` (the posteriors overlaid, truth in red), ``trace_<sampler>.png``
(log-density per iteration), ``results.json`` and ``results.md``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # `python experiments/baselines.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np

from experiments import common as C

STUDY = "baselines"
EPILOG = """\
examples:
  python experiments/baselines.py --size cpu              # minutes on a CPU (default)
  python experiments/baselines.py --size full             # the paper's scale, for a GPU
  python experiments/baselines.py --size tiny --out /tmp/b --samplers nnsvgd,mh

sizes: tiny (tests), cpu (R=3, 12 particles, 50 iterations, 2 training / 8 test trajectories of
1 s), full (R=3, 128 particles, 300 iterations, 5 training / 25 test trajectories of 3 s).
"""


PAPER_SGHMC = {"step_size": 1e-4, "learning_rate": 0.05, "alpha": 0.1}


def _samplers(text: str) -> tuple[str, ...]:
    names = tuple(s.strip().lower() for s in text.split(",") if s.strip())
    bad = [s for s in names if s not in C.ALL_SAMPLERS]
    if bad or not names:
        import argparse

        raise argparse.ArgumentTypeError(
            f"unknown sampler(s) {bad}; choose from {','.join(C.ALL_SAMPLERS)}"
        )
    return names


def build_parser():
    p = C.build_parser(STUDY, __doc__.split("\n\n")[0] + "\n\n" + __doc__.split("\n\n")[1], EPILOG)
    p.add_argument(
        "--samplers",
        type=_samplers,
        default=None,
        help=f"comma-separated subset (default all: {','.join(C.ALL_SAMPLERS)})",
    )
    return p


def run(argv=None) -> int:
    args = build_parser().parse_args(argv)
    C.setup_jax()
    # the paper's SGHMC baseline (Adam drift, small step): treeinfer's own SGHMC defaults
    # changed to true SGHMC that moves (issue 11; experiments/sghmc_defaults.py)
    ctx = C.context_from_args(
        STUDY, args, samplers=args.samplers, sampler_options={"sghmc": PAPER_SGHMC}
    )
    cfg, seed = ctx.cfg, ctx.seed
    t0 = time.perf_counter()
    bar = C.progress_bar(ctx, 2 + len(cfg.samplers))
    C.say(ctx, "simulating ground truth (plain MuJoCo)")
    data = C.make_data(cfg, seed, ctx.sims)
    bar.update()

    problems: dict[bool, object] = {}
    conditions, bands, sets, figures = [], {}, {}, {}
    plot_idx = list(range(min(cfg.n_plot, len(data.test))))
    for sampler in cfg.samplers:
        nn = C.REGISTRY[sampler].nn_prior  # the baselines use the smoothed box prior alone
        if nn not in problems:
            problems[nn] = C.make_problem(cfg, data, nn_prior=nn)
        problem = problems[nn]
        C.say(ctx, f"{sampler}: {cfg.n_particles} particles x {cfg.n_iterations} iterations")
        post = C.posterior(problem, sampler, cfg, seed, ctx.cache, ctx.progress)
        pred, m = C.evaluate(problem, post, data, cfg)
        name = C.SAMPLER_LABELS[sampler]
        conditions.append(
            {
                "name": name,
                "sampler": sampler,
                "nn_prior": nn,
                "metrics": m,
                "inference": C.inference_record(post),
            }
        )
        bands[name] = C.bands_for(pred, data, plot_idx, cfg.level)
        sets[name] = post.theta[np.all(np.isfinite(post.theta), axis=1)]
        figures[f"trace_{sampler}.png"] = _trace_figure(post, name)
        bar.update()

    problem = next(iter(problems.values()))
    figures["bands.png"] = C.band_grid(
        bands,
        cfg.dt,
        cfg.level,
        [f"test {i}" for i in plot_idx],
        "Baselines: 95% predictive bands on unseen test trajectories",
    )
    figures["metrics.png"] = C.metric_figure(
        [c["name"] for c in conditions], [c["metrics"] for c in conditions], "Baselines"
    )
    figures["pairs.png"] = C.pair_figure(
        sets, problem.labels, data.theta, "Posteriors (ln K); truth in red"
    )
    record = {
        "data": C.data_record(data, problem),
        "conditions": conditions,
        "metric_notes": C.METRIC_NOTES,
    }
    C.write_results(ctx, record, _markdown(cfg, data, problem, conditions), figures, t0)
    bar.update()
    bar.close()
    C.say(ctx, f"wrote {ctx.out}/ in {time.perf_counter() - t0:.0f} s")
    return 0


def _trace_figure(post, name: str):
    from treeinfer.evaluation.plots import plot_trace

    fig, _ = plot_trace(
        post.trace_logdensity,
        iterations=post.trace_iterations,
        title=f"{name}: log posterior density",
    )
    return fig


def _markdown(cfg, data, problem, conditions) -> str:
    rows = [
        [c["name"]]
        + C.metric_cells(c["metrics"])
        + [C.fmt(c["inference"]["sampler_wall_s"], ".0f")]
        for c in conditions
    ]
    table = C.markdown_table(["sampler"] + C.METRIC_HEADERS + ["sampler time [s]"], rows)
    params = C.parameter_table(
        [(c["name"], c["metrics"]) for c in conditions], problem.labels, data.theta
    )
    return "\n\n".join(
        [
            "# (a) Baselines: NNSVGD vs SVGD, SGHMC, SGLD, MH (paper Fig. 3)",
            C.config_line(cfg, data, problem) + ".",
            table,
            "Posterior means of ln K with 95% marginal intervals:",
            params,
            (
                "Figures: `bands.png` (rows: samplers; columns: unseen test trajectories), "
                "`metrics.png`, "
                "`pairs.png`, `trace_<sampler>.png`. Sampler time is the sampler's own wall time "
                "when it "
                "ran (compilation included; a cached posterior keeps the time of the run that made "
                "it)."
            ),
            C.METRIC_NOTES,
        ]
    )


def main(argv=None) -> int:
    return C.run_main(run, argv, STUDY)


if __name__ == "__main__":
    sys.exit(main())
