"""(b) The NN inequality prior's benefit (paper Table I and Fig. 4): NNSVGD against SVGD.

Same sim-to-sim problem as the baselines (the two posteriors are shared with them through the
posterior cache). Table I's quantities on the unseen test trajectories: the average 95% CI
width, the % of ground-truth points outside it and an NLL (see results.md for our exact
definitions: the paper does not give its own); Fig. 4: both posteriors overlaid in a pair plot
with the true parameters.

Outputs in ``experiments/results/nn_prior/``: ``pairs.png``, ``bands.png``, ``metrics.png``,
``results.json``, ``results.md``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # `python experiments/nn_prior.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np

from experiments import common as C

STUDY = "nn_prior"
PAPER_TABLE_I = {
    "NNSVGD": {"ci_width": 0.11, "pct_outside": "<1", "nll": 2268.1},
    "SVGD": {"ci_width": 0.19, "pct_outside": "<1", "nll": 3050.7},
}
EPILOG = """\
examples:
  python experiments/nn_prior.py --size cpu      # minutes on a CPU (default)
  python experiments/nn_prior.py --size full     # 128 particles, 25 unseen test trajectories (GPU)
"""


def build_parser():
    doc = __doc__.split("\n\n")
    return C.build_parser(STUDY, doc[0] + "\n\n" + doc[1], EPILOG)


def run(argv=None) -> int:
    args = build_parser().parse_args(argv)
    C.setup_jax()
    ctx = C.context_from_args(STUDY, args)
    cfg, seed = ctx.cfg, ctx.seed
    t0 = time.perf_counter()
    bar = C.progress_bar(ctx, 2 + len(cfg.samplers))
    C.say(ctx, "simulating ground truth (plain MuJoCo)")
    data = C.make_data(cfg, seed, ctx.sims)
    bar.update()

    conditions, bands, sets = [], {}, {}
    plot_idx = list(range(min(cfg.n_plot, len(data.test))))
    problem = None
    for sampler in cfg.samplers:
        nn = C.REGISTRY[sampler].nn_prior
        problem = C.make_problem(cfg, data, nn_prior=nn)
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
        bar.update()

    figures = {
        "pairs.png": C.pair_figure(
            sets, problem.labels, data.theta, "NNSVGD vs SVGD posteriors (ln K); truth in red"
        ),
        "bands.png": C.band_grid(
            bands,
            cfg.dt,
            cfg.level,
            [f"test {i}" for i in plot_idx],
            "95% predictive bands on unseen test trajectories",
        ),
        "metrics.png": C.metric_figure(
            [c["name"] for c in conditions], [c["metrics"] for c in conditions], "NN prior benefit"
        ),
    }
    record = {
        "data": C.data_record(data, problem),
        "conditions": conditions,
        "paper_table_I": PAPER_TABLE_I,
        "metric_notes": C.METRIC_NOTES,
    }
    C.write_results(ctx, record, _markdown(cfg, data, problem, conditions), figures, t0)
    bar.update()
    bar.close()
    C.say(ctx, f"wrote {ctx.out}/ in {time.perf_counter() - t0:.0f} s")
    return 0


def _markdown(cfg, data, problem, conditions) -> str:
    rows = [[c["name"]] + C.metric_cells(c["metrics"]) for c in conditions]
    table = C.markdown_table(["sampler"] + C.METRIC_HEADERS, rows)
    paper = C.markdown_table(
        ["paper (Table I)", "95% CI width", "% GT outside CI", "Nll"],
        [[k, v["ci_width"], v["pct_outside"], v["nll"]] for k, v in PAPER_TABLE_I.items()],
    )
    params = C.parameter_table(
        [(c["name"], c["metrics"]) for c in conditions], problem.labels, data.theta
    )
    return "\n\n".join(
        [
            "# (b) NN prior benefit: NNSVGD vs SVGD (paper Table I, Fig. 4)",
            C.config_line(cfg, data, problem) + ".",
            table,
            "The paper's Table I (Isaac Gym, 25 unseen test trajectories, its own NLL definition "
            "and units):",
            paper,
            "Posterior means of ln K with 95% marginal intervals:",
            params,
            "Figures: `pairs.png` (Fig. 4: both posteriors, truth in red), `bands.png`, "
            "`metrics.png`.",
            C.METRIC_NOTES,
        ]
    )


def main(argv=None) -> int:
    return C.run_main(run, argv, STUDY)


if __name__ == "__main__":
    sys.exit(main())
