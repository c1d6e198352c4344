"""Where to pull next: does the pull that ``treeinfer.design`` ranks first teach more?

Protocol, per seed (sim-to-sim, as in the other studies: ground truth from plain MuJoCo C in
float64, inference with the batched simulator):

1. True gains drawn as ``treeinfer simulate`` does
   (:func:`treeinfer.sim.synthetic.default_true_params`).
2. **First pull** at the tip (grasp fraction 1), a ramp-hold-release (``hold`` profile) of
   ``first_peak`` N, with white Gaussian noise of ``noise_mm`` on the displacement; posterior 1
   by NNSVGD with the likelihood temperature of that noise, velocity term included
   (:func:`treeinfer.model.likelihood.suggest_kT` with ``omega2`` of the data set).
3. **Score** the candidate second pulls (grasp fractions x peak forces x profile kinds) at
   posterior 1 (``sigma_x`` = the noise) with :func:`treeinfer.design.score_candidates`.
4. **Second pulls**, each a new noisy recording: ``design`` (ranked first by the Laplace EIG),
   ``design_target`` (ranked first by the expected reduction of the held-out manipulation's
   predictive variance, ``target=``: the criterion to use when the future manipulation is known),
   ``design_worst`` (ranked first by the expected variance reduction of the parameter with the
   largest std after pull 1, ``parameter="worst"``), ``repeat`` (the first pull again, fresh
   noise), ``random`` (a seeded uniform pick among the candidates). For each, the posterior of
   both pulls together, with the same inference settings and sampler seed as every other arm.
5. Report the posterior std (log units) of every parameter after pull 1 and after each second
   pull, and the width of the 95% predictive band at the held-out manipulation (a ``hold`` pull
   of ``heldout_peak`` N at grasp fraction ``heldout_grasp``, not among the candidates), averaged
   over its samples. Beside them, as an independent reference, the Cramér-Rao std of every
   parameter and the linearised held-out band (``3.92 sqrt(G C G^T)``) from the Fisher
   information of the pulls at the true parameters (Gaussian noise of ``noise_mm``).

**Inference (why not the uniform start).** NNSVGD from particles uniform in the prior box with a
constant Adam step (the settings of the first version of this study) is far from converged
here: on identical data, three sampler seeds gave held-out bands of 22, 182 and 207 mm and
particles 150 nats below the best one, while the Fisher information at the truth gives a band
of ~4 mm; the arms' bands then differed by sampler noise, not by their data. So every posterior
here (all arms alike) starts from draws of the Laplace approximation around a Levenberg-Marquardt
MAP fit of *its own* data (:func:`treeinfer.inference.fit_map`, as ``treeinfer infer --init
laplace``; widened ``laplace_scale`` x), and NNSVGD's Adam step decays along a cosine from
``learning_rate`` to ``final_learning_rate`` so the particles settle (``init="uniform"`` and
``final_learning_rate=None`` give the old behaviour). The first version also set kT for the
displacement term alone (``omega2 = 0``), which leaves the velocity term of the loss untempered:
its posteriors came out ~3-4x narrower than the Cramér-Rao bound (``kT_velocity``). All
posteriors of a stage run as one batched program
(:func:`treeinfer.inference.posterior_program`, ``batch`` data sets per call).

Targets (issue 16): the design pull shrinks the std of the worst-identified parameter (largest
std after pull 1) at least 2x more than the repeat (median over seeds), and never widens the
held-out band relative to after pull 1.

Sizes: ``tiny`` (smoke test, 2-branch), ``cpu`` (5 seeds, minutes here), ``full`` (20 seeds,
the paper's particle counts, for a GPU). Results: ``results.json``, ``results.md`` and figures in
``experiments/results/design`` (``full``: ``experiments/results/full/design``).

    python experiments/design_study.py --size cpu
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from experiments._design_config import SIZES, STUDY, DesignConfig, _say  # noqa: E402
from experiments._design_posteriors import run_seeds  # noqa: E402
from experiments._design_summary import (  # noqa: E402
    CONDITIONS,
    _figures,
    _markdown,
    _suggestions_from_dict,
    summarise,
)
from experiments.common import (  # noqa: E402
    RESULTS,
    check_out,
    cpu_seconds,
    run_main,
    setup_jax,
    tree_path,
    versions,
)

__all__ = ["CONDITIONS", "SIZES", "DesignConfig", "build_parser", "main", "run_seeds"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python experiments/design_study.py",
        description=__doc__.split("\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--size",
        choices=tuple(SIZES),
        default="cpu",
        help="tiny, cpu (5 seeds) or full (20 seeds, GPU)",
    )
    p.add_argument("--seeds", type=int, default=None, help="override the number of seeds")
    p.add_argument("--seed", type=int, default=0, help="first seed (default 0)")
    p.add_argument("--particles", type=int, default=None, help="override NNSVGD's particle count")
    p.add_argument("--iterations", type=int, default=None, help="override NNSVGD's iteration count")
    p.add_argument(
        "--init",
        choices=("laplace", "uniform"),
        default=None,
        help="particle start of every posterior (default laplace: MAP fit + Laplace draws)",
    )
    p.add_argument(
        "--batch", type=int, default=None, help="data sets per batched sampler call (default 128)"
    )
    p.add_argument("--out", type=Path, default=None, help="results folder")
    p.add_argument("--quiet", action="store_true")
    p.add_argument(
        "--resummarise",
        action="store_true",
        help="recompute the summary, markdown and figures of --out's results.json (no inference)",
    )
    return p


def _resummarise(out: Path) -> int:
    """Recompute summary, markdown and figures from ``out/results.json`` (no inference)."""
    import json

    from treeinfer.evaluation import save_figure
    from treeinfer.io.atomic import atomic_write_json, atomic_write_text, staged_output_dir

    record = json.loads((out / "results.json").read_text())
    sugg_d = json.loads((out / "suggestions_seed0.json").read_text())
    conf = {k: tuple(v) if isinstance(v, list) else v for k, v in record["config"].items()}
    if "init" not in conf:  # a record of the first version: uniform start, constant Adam step
        conf.update(init="uniform", final_learning_rate=None, kT_velocity=False)
    cfg = DesignConfig(**conf)
    seeds = record["seeds"]
    record["summary"] = summarise(seeds, record["summary"]["labels"])
    md = _markdown(cfg, record["summary"], seeds, record["wall_time_s"], record["cpu_time_s"])
    figures = _figures(record["summary"], _suggestions_from_dict(sugg_d))
    with staged_output_dir(out, force=True, what="results") as stage:
        for name, fig in figures.items():
            save_figure(fig, stage / name)
        atomic_write_json(stage / "results.json", record)
        atomic_write_text(stage / "results.md", md)
        atomic_write_json(stage / "suggestions_seed0.json", sugg_d)
    print(md)
    return 0


def main(argv=None, programs=None) -> int:
    """The study (see the module docstring). ``programs``: a
    :class:`treeinfer.sim.program_cache.ProgramCache` for the batched programs (the caller's, to
    reuse them across calls; None: this call's)."""
    args = build_parser().parse_args(argv)
    over = {
        k: v
        for k, v in (
            ("seeds", args.seeds),
            ("n_particles", args.particles),
            ("n_iterations", args.iterations),
            ("init", args.init),
            ("batch", args.batch),
        )
        if v is not None
    }
    cfg = DesignConfig(size=args.size, **{**SIZES[args.size], **over})
    out = args.out or (RESULTS / "full" / STUDY if args.size == "full" else RESULTS / STUDY)
    check_out(out)
    if args.resummarise:
        return _resummarise(Path(out))
    setup_jax()
    from treeinfer import make_simulator
    from treeinfer.evaluation import save_figure
    from treeinfer.io.atomic import atomic_write_json, atomic_write_text, staged_output_dir
    from treeinfer.tree import load_tree

    t0 = time.perf_counter()
    tree = load_tree(tree_path(cfg.tree))
    sim = make_simulator(tree, obs_dt=cfg.dt)
    seeds, first_sugg = run_seeds(
        cfg, tree, sim, list(range(args.seed, args.seed + cfg.seeds)), args.quiet, programs
    )
    summary = summarise(seeds, tree.parameter_labels())
    wall = time.perf_counter() - t0
    record = {
        "study": STUDY,
        "size": cfg.size,
        "first_seed": args.seed,
        "config": dataclasses.asdict(cfg),
        "versions": versions(),
        "command": " ".join(["experiments/design_study.py"] + list(argv or sys.argv[1:])),
        "summary": summary,
        "seeds": seeds,
        "wall_time_s": wall,
        "cpu_time_s": cpu_seconds(),
    }
    # the record's CPU time, so --resummarise rebuilds this markdown exactly
    md = _markdown(cfg, summary, seeds, wall, record["cpu_time_s"])
    figures = _figures(summary, first_sugg)
    with staged_output_dir(out, force=True, what="results") as stage:
        for name, fig in figures.items():
            save_figure(fig, stage / name)
        atomic_write_json(stage / "results.json", record)
        atomic_write_text(stage / "results.md", md)
        atomic_write_json(stage / "suggestions_seed0.json", first_sugg.to_dict())
    _say(args.quiet, f"wrote {out} in {wall:.0f} s")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(run_main(main, sys.argv[1:], STUDY))
