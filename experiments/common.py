"""Shared machinery of the paper's sim-to-sim studies (``experiments/<study>.py``).

One study = one :class:`StudyConfig` (sizes ``tiny`` / ``cpu`` / ``full``), synthetic data with
known parameters (:func:`make_data`), one posterior per condition (:func:`posterior`), the
paper's metrics on unseen test trajectories (:func:`evaluate`), and a results folder
(:func:`write_results`: ``results.json``, ``results.md``, PNGs, written atomically).

Sim-to-sim protocol (paper, "Sim-to-sim"):

* **Ground truth** comes from plain MuJoCo (C, float64:
  :func:`treeinfer.sim.reference.simulate_reference`), an execution path independent of the
  batched MJX simulator (float32) that inference uses; only the force-deformation trajectories
  pass from one to the other. True parameters are drawn by
  :func:`treeinfer.sim.synthetic.default_true_params` (log-uniform in the middle third of the prior
  box, parent >= child), as ``treeinfer simulate`` does.
* **Training and test sets** use different force profiles drawn from independent seed streams
  (``numpy.random.SeedSequence(seed).spawn``): the test trajectories are never seen by inference.
* **Seeds**: ``--seed S`` fixes the true parameters, the profiles, the noise and the sampler
  key; the same seed gives the same numbers (JAX on one device is deterministic).

Compute on a small CPU: MJX compiles every new program for 30-120 s, so the studies share
everything they can. All studies of one size use the same tree, true parameters and training
set, and a posterior is cached on disk under a key of everything that determines it
(:func:`posterior`): NNSVGD and SVGD of the baselines are reused by the NN-prior study, NNSVGD by
the noise study's sigma = 0 and by the grasp study. Predictions of a study go through one
jitted call whose shape is the same in every study of a size.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as `python experiments/<study>.py` from anywhere
    sys.path.insert(0, str(ROOT))

from experiments._config import (  # noqa: E402  (re-exported: scripts import them from here)
    ALL_SAMPLERS,
    BASE_SIZES,
    EXAMPLES,
    RESULTS,
    SAMPLER_LABELS,
    SIZES,
    STUDIES,
    STUDY_SIZES,
    Context,
    StudyConfig,
    study_config,
    tree_path,
)
from treeinfer.errors import ConfigError, OutputExistsError, TreeinferError
from treeinfer.inference import REGISTRY


# ==== command line ================================================================================
def build_parser(study: str, description: str, epilog: str = "") -> argparse.ArgumentParser:
    """The options every study script shares: ``--size``, ``--out``, ``--seed``, caches, quiet."""
    p = argparse.ArgumentParser(
        prog=f"python experiments/{study}.py",
        description=description,
        epilog=epilog,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--size",
        choices=SIZES,
        default="cpu",
        help="tiny (tests), cpu (minutes here) or full (paper scale, GPU); default cpu",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help=f"results folder (default experiments/results/{study}); replaced if it holds an "
        "earlier results.json",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the true parameters, profiles, noise and samplers (default 0)",
    )
    p.add_argument("--particles", type=int, default=None, help="override the size's particle count")
    p.add_argument(
        "--iterations", type=int, default=None, help="override the size's iteration count"
    )
    p.add_argument(
        "--cache",
        type=Path,
        default=None,
        help="posterior cache folder (default $TREEINFER_CACHE/posteriors or "
        "~/.cache/treeinfer/posteriors)",
    )
    p.add_argument(
        "--no-cache", action="store_true", help="neither read nor write cached posteriors"
    )
    p.add_argument(
        "--likelihood",
        choices=("boltzmann", "gaussian", "student_t", "ar1"),
        default=None,
        help="boltzmann (the paper's loss, default) or a generative noise model whose sigma_x is "
        "inferred unless --noise-displacement fixes it; the headline band is then predictive",
    )
    p.add_argument(
        "--noise-displacement",
        type=float,
        default=None,
        metavar="M",
        help="fixed displacement noise sigma_x in m for the generative likelihoods",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def setup_jax() -> None:
    """Persistent XLA cache (MJX compiles slowly; a rerun of the same shapes skips it)."""
    import treeinfer

    treeinfer.enable_compilation_cache()


def context_from_args(study: str, args: argparse.Namespace, **overrides) -> Context:
    cfg = study_config(
        study,
        args.size,
        n_particles=args.particles,
        n_iterations=args.iterations,
        likelihood=getattr(args, "likelihood", None),
        noise_displacement=getattr(args, "noise_displacement", None),
        **overrides,
    )
    if args.no_cache:
        cache = None
    elif args.cache is not None:
        cache = args.cache
    else:
        from treeinfer.model import default_cache_dir

        cache = default_cache_dir() / "posteriors"
    out = args.out if args.out is not None else RESULTS / study
    check_out(out)
    from treeinfer.runs import SimulatorCache

    return Context(cfg, int(args.seed), cache, Path(out), not args.quiet, SimulatorCache())


def check_out(out: Path) -> None:
    """Refuse a non-empty folder that does not hold an earlier study result (never clobber
    others' files)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise OutputExistsError(f"{out}: output path exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / "results.json").exists():
        raise OutputExistsError(
            f"{out}: folder holds other files (no results.json); choose another --out"
        )


def run_main(fn, argv, study: str) -> int:
    """Run a study's ``main`` body with treeinfer's user-facing error handling (exit 2)."""
    try:
        return fn(argv)
    except TreeinferError as e:
        print(f"{study}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{study}: interrupted; nothing was written", file=sys.stderr)
        return 130


def say(ctx: Context, msg: str) -> None:
    if ctx.progress:
        from tqdm.auto import tqdm

        tqdm.write(f"[{ctx.cfg.study}] {msg}", file=sys.stderr)


# ==== the rest of the machinery lives in experiments/_*.py; re-exported here ===================
from experiments._data import (  # noqa: E402
    SyntheticData,
    add_relative_noise,
    make_data,
    noise_sigmas,
    reference_trajectory,
    seed_streams,
)
from experiments._evaluation import (  # noqa: E402
    Bands,
    Predictions,
    band_grid,
    bands_for,
    evaluate,
    inference_record,
    interval_metrics,
    metric_figure,
    metrics_for,
    pair_figure,
    parameter_metrics,
    predict_all,
)
from experiments._posterior_cache import (  # noqa: E402
    PosteriorRun,
    make_problem,
    posterior,
    posterior_key,
)
from experiments._tables import (  # noqa: E402
    METRIC_HEADERS,
    METRIC_NOTES,
    config_line,
    cpu_seconds,
    data_record,
    fmt,
    markdown_table,
    metric_cells,
    parameter_table,
    progress_bar,
    versions,
    write_results,
)

__all__ = [
    "ALL_SAMPLERS",
    "BASE_SIZES",
    "Bands",
    "ConfigError",
    "Context",
    "EXAMPLES",
    "METRIC_HEADERS",
    "METRIC_NOTES",
    "PosteriorRun",
    "Predictions",
    "REGISTRY",
    "RESULTS",
    "SAMPLER_LABELS",
    "SIZES",
    "STUDIES",
    "STUDY_SIZES",
    "StudyConfig",
    "SyntheticData",
    "add_relative_noise",
    "band_grid",
    "bands_for",
    "build_parser",
    "check_out",
    "config_line",
    "context_from_args",
    "cpu_seconds",
    "data_record",
    "evaluate",
    "fmt",
    "inference_record",
    "interval_metrics",
    "make_data",
    "make_problem",
    "markdown_table",
    "metric_cells",
    "metric_figure",
    "metrics_for",
    "noise_sigmas",
    "pair_figure",
    "parameter_metrics",
    "parameter_table",
    "posterior",
    "posterior_key",
    "predict_all",
    "progress_bar",
    "reference_trajectory",
    "run_main",
    "say",
    "seed_streams",
    "setup_jax",
    "study_config",
    "tree_path",
    "versions",
    "write_results",
]
