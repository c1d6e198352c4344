"""(d) Unseen grasp locations (paper Fig. 6): infer at one grasp point, predict at others.

NNSVGD is trained on the clean training set recorded at the tree's grasp point (the tip of the
grasped branch for the 3-branch example: fraction 1.0 of its length; the same posterior as the
baselines' NNSVGD). Unseen test profiles are then pulled at 0.25, 0.5, 0.75 and 1.0 of the
grasped branch's length from its parent joint, with ground truth simulated from the true
parameters at each location (plain MuJoCo), and every particle predicts each of them
(``treeinfer.predict(..., grasp_fraction=...)``). At 1.0 the location is the training one but the
force profiles are unseen. Unlike the paper's Fig. 6 we add no noise here (the noise study
covers it), so the grasp effect is seen alone.

Outputs in ``experiments/results/grasp/``: ``bands.png`` (one row per location), ``metrics.png``,
``results.json``, ``results.md``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # `python experiments/grasp.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np

from experiments import common as C

STUDY = "grasp"
EPILOG = """\
examples:
  python experiments/grasp.py --size cpu       # 2 unseen profiles at each of 4 locations
  python experiments/grasp.py --size full      # 25 unseen profiles at each location (GPU)
  python experiments/grasp.py --size cpu --locations 0.3,0.6,0.9
"""


def _locations(text: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(s) for s in text.split(",") if s.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated fractions, got {text!r}"
        ) from None
    if not vals:
        raise argparse.ArgumentTypeError("give at least one location")
    return vals


def build_parser():
    doc = __doc__.split("\n\n")
    p = C.build_parser(STUDY, doc[0] + "\n\n" + doc[1], EPILOG)
    p.add_argument(
        "--locations",
        type=_locations,
        default=None,
        metavar="F1,F2,..",
        help="test grasp fractions in (0, 1] (default 0.25,0.5,0.75,1.0)",
    )
    return p


def location_name(f: float) -> str:
    return f"loc {f:g} l"


def run(argv=None) -> int:
    args = build_parser().parse_args(argv)
    C.setup_jax()
    ctx = C.context_from_args(STUDY, args, grasp_locations=args.locations)
    cfg, seed = ctx.cfg, ctx.seed
    t0 = time.perf_counter()
    bar = C.progress_bar(ctx, 3)
    C.say(ctx, "simulating ground truth at every location (plain MuJoCo)")
    data = C.make_data(cfg, seed, ctx.sims)
    bar.update()

    problem = C.make_problem(cfg, data, nn_prior=True)
    C.say(
        ctx,
        f"NNSVGD at grasp {data.tree.grasp_fraction:g}: {cfg.n_particles} particles x "
        f"{cfg.n_iterations} iterations",
    )
    post = C.posterior(problem, "nnsvgd", cfg, seed, ctx.cache, ctx.progress)
    groups = {
        location_name(f): np.flatnonzero(np.isclose(data.test_grasp, f))
        for f in cfg.grasp_locations
    }
    pred, per_loc = C.evaluate(problem, post, data, cfg, groups)
    bar.update()

    conditions, bands = [], {}
    n_cols = min(cfg.n_plot, cfg.n_test_per_location)
    for f, (name, idx) in zip(cfg.grasp_locations, groups.items()):
        conditions.append({"name": name, "grasp_fraction": f, "metrics": per_loc[name]})
        bands[name] = C.bands_for(pred, data, idx[:n_cols], cfg.level)
    figures = {
        "bands.png": C.band_grid(
            bands,
            cfg.dt,
            cfg.level,
            [f"profile {i}" for i in range(n_cols)],
            f"Trained at grasp {data.tree.grasp_fraction:g} l; 95% bands at the test locations",
            transpose=True,
        ),
        "metrics.png": C.metric_figure(
            [c["name"] for c in conditions],
            [c["metrics"] for c in conditions],
            "Unseen grasp locations",
        ),
    }
    record = {
        "data": C.data_record(data, problem),
        "train_grasp_fraction": data.tree.grasp_fraction,
        "inference": C.inference_record(post),
        "conditions": conditions,
        "metric_notes": C.METRIC_NOTES,
    }
    C.write_results(ctx, record, _markdown(cfg, data, problem, conditions, post), figures, t0)
    bar.update()
    bar.close()
    C.say(ctx, f"wrote {ctx.out}/ in {time.perf_counter() - t0:.0f} s")
    return 0


def _markdown(cfg, data, problem, conditions, post) -> str:
    rows = [
        [c["name"]] + C.metric_cells(c["metrics"])[:3] + [C.metric_cells(c["metrics"])[-1]]
        for c in conditions
    ]
    table = C.markdown_table(
        ["test location"] + C.METRIC_HEADERS[:3] + [C.METRIC_HEADERS[-1]], rows
    )
    m0 = conditions[0]["metrics"]
    post_line = (
        f"Posterior (shared by all locations): |log error| "
        f"{C.fmt(m0.get('mean_abs_log_error'), '.2f')}, "
        f"{m0.get('n_params_in_interval', 0)}/{m0.get('n_params', 0)} true parameters in their 95% "
        f"interval, "
        f"posterior NLL (train) {C.fmt(m0.get('posterior_nll'), '.4g')}."
        if "error" not in m0
        else "Posterior: no stable particles."
    )
    return "\n\n".join(
        [
            "# (d) Unseen grasp locations (paper Fig. 6)",
            C.config_line(
                cfg,
                data,
                problem,
                f"{len(data.test)} unseen test ({cfg.n_test_per_location} profiles x "
                f"{len(cfg.grasp_locations)} locations)",
            )
            + f"; trained at grasp fraction {data.tree.grasp_fraction:g} of branch "
            f"`{data.tree.grasp_branch}`, no noise.",
            table,
            post_line,
            (
                "Figures: `bands.png` (columns: test grasp locations as fractions of the branch "
                "length l from its "
                "parent joint; rows: unseen force profiles), `metrics.png`."
            ),
            C.METRIC_NOTES,
        ]
    )


def main(argv=None) -> int:
    return C.run_main(run, argv, STUDY)


if __name__ == "__main__":
    sys.exit(main())
