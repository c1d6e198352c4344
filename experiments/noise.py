"""(c) Robustness to sensor noise (paper Fig. 5): NNSVGD on noisy force and displacement.

For each relative noise level s, white Gaussian noise of standard deviation
``sigma_F = s * max|F|`` (N) is added to every force sample and ``sigma_x = s * max|x|`` (m) to
every displacement sample, the maxima taken over all clean training and test trajectories of the
data set (the paper: "sigma, measured relative to the force"; we scale the displacement noise the
same way relative to the displacement). Noise hits the training set (inference sees noisy data;
velocities are differentiated from the noisy displacement, as for a recording) and the test set:
predictions are driven by the noisy test forces and compared with the noisy test displacements,
as a user would compare with a noisy recording. kT stays fixed across levels.

Outputs in ``experiments/results/noise/``: ``bands.png`` (one row per level), ``metrics.png``
(CI width and % GT outside per level, the paper's bar chart), ``results.json``, ``results.md``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # `python experiments/noise.py`
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np

from experiments import common as C

STUDY = "noise"
EPILOG = """\
examples:
  python experiments/noise.py --size cpu                     # levels 0, 0.02, 0.1
  python experiments/noise.py --size full                    # levels 0, 0.01, 0.02, 0.05, 0.1
  python experiments/noise.py --size cpu --levels 0,0.05
"""


def _levels(text: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(s) for s in text.split(",") if s.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers, got {text!r}"
        ) from None
    if not vals:
        raise argparse.ArgumentTypeError("give at least one level")
    return vals


def build_parser():
    doc = __doc__.split("\n\n")
    p = C.build_parser(STUDY, doc[0] + "\n\n" + doc[1], EPILOG)
    p.add_argument(
        "--levels",
        type=_levels,
        default=None,
        metavar="S1,S2,..",
        help="relative noise levels (fractions of each signal's peak)",
    )
    return p


def level_name(level: float) -> str:
    return f"sigma {100 * level:g}%"


def run(argv=None) -> int:
    args = build_parser().parse_args(argv)
    C.setup_jax()
    ctx = C.context_from_args(STUDY, args, noise_levels=args.levels)
    cfg, seed = ctx.cfg, ctx.seed
    t0 = time.perf_counter()
    bar = C.progress_bar(ctx, 2 + len(cfg.noise_levels))
    C.say(ctx, "simulating ground truth (plain MuJoCo)")
    clean = C.make_data(cfg, seed, ctx.sims)
    bar.update()

    conditions, bands = [], {}
    plot_idx = list(range(min(cfg.n_plot, len(clean.test))))
    problem = None
    for level in cfg.noise_levels:
        data, noise = C.add_relative_noise(clean, level, seed)
        problem = C.make_problem(cfg, data, nn_prior=True)
        C.say(
            ctx,
            f"{level_name(level)}: NNSVGD, {cfg.n_particles} particles x {cfg.n_iterations} "
            f"iterations",
        )
        post = C.posterior(problem, "nnsvgd", cfg, seed, ctx.cache, ctx.progress)
        pred, m = C.evaluate(problem, post, data, cfg)
        name = level_name(level)
        vs_clean = C.interval_metrics(pred, np.stack([t.displacement for t in clean.test]), cfg)
        conditions.append(
            {
                "name": name,
                "noise": noise,
                "sampler": "nnsvgd",
                "metrics": m,
                "metrics_vs_clean_truth": vs_clean,
                "inference": C.inference_record(post),
            }
        )
        bands[name] = C.bands_for(pred, data, plot_idx, cfg.level)
        bar.update()

    figures = {
        "bands.png": C.band_grid(
            bands,
            cfg.dt,
            cfg.level,
            [f"test {i}" for i in plot_idx],
            "NNSVGD under noise: 95% bands vs noisy ground truth",
        ),
        "metrics.png": C.metric_figure(
            [c["name"] for c in conditions],
            [c["metrics"] for c in conditions],
            "Robustness to noise",
            keys={"95% CI width [m]": "ci_width", "% GT outside": "pct_outside"},
        ),
    }
    record = {
        "data": C.data_record(clean, problem),
        "noise_definition": (
            "sigma_F = level * max|F|, sigma_x = level * max|x| over the clean training and test "
            "trajectories; white Gaussian, added to training and test force and displacement"
        ),
        "conditions": conditions,
        "metric_notes": C.METRIC_NOTES,
    }
    C.write_results(ctx, record, _markdown(cfg, clean, problem, conditions), figures, t0)
    bar.update()
    bar.close()
    C.say(ctx, f"wrote {ctx.out}/ in {time.perf_counter() - t0:.0f} s")
    return 0


def _markdown(cfg, data, problem, conditions) -> str:
    rows = [
        [
            c["name"],
            C.fmt(c["noise"]["sigma_force_N"], ".3g"),
            C.fmt(1e3 * c["noise"]["sigma_displacement_m"], ".3g"),
        ]
        + C.metric_cells(c["metrics"])
        for c in conditions
    ]
    table = C.markdown_table(["noise", "sigma_F [N]", "sigma_x [mm]"] + C.METRIC_HEADERS, rows)
    clean_rows = [
        [
            c["name"],
            C.fmt(c["metrics_vs_clean_truth"].get("pct_outside"), ".1f"),
            C.fmt(c["metrics_vs_clean_truth"].get("predictive_nll_per_point"), ".2f"),
        ]
        for c in conditions
    ]
    clean_table = C.markdown_table(
        ["noise", "% clean GT outside", "NLL / clean test point"], clean_rows
    )
    return "\n\n".join(
        [
            "# (c) Robustness to Gaussian noise on force and displacement (paper Fig. 5)",
            C.config_line(cfg, data, problem) + "; NNSVGD at every level.",
            (
                "Noise: sigma_F = s * max|F| and sigma_x = s * max|x|, maxima over the clean "
                "training and test "
                "trajectories; added to training and test trajectories; the metrics compare the "
                "bands with "
                "the noisy test displacement."
            ),
            table,
            (
                "The same bands against the noise-free test displacement (did the posterior "
                "recover the "
                "motion underneath the noise?):"
            ),
            clean_table,
            (
                "Figures: `bands.png` (rows: noise levels; columns: unseen test trajectories; red: "
                "the noisy "
                "ground truth), `metrics.png`."
            ),
            C.METRIC_NOTES,
        ]
    )


def main(argv=None) -> int:
    return C.run_main(run, argv, STUDY)


if __name__ == "__main__":
    sys.exit(main())
