"""``treeinfer amortise``: train an amortised posterior of a tree (:mod:`treeinfer.amortised`),
and the part of ``treeinfer infer --amortised M`` that loads it, refuses it for another tree or
layout and prints its answer (:func:`amortised_for_infer`)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..data.forces import DEFAULT_PEAK_RANGE, SET_KINDS
from ..errors import ConfigError
from .common import (
    COMMAND_HELP,
    EXIT_OK,
    _pair,
    _prepare_jax,
    _say,
    add_backend_option,
    add_command_parser,
    add_out_option,
)

_EPILOG = """\
examples:
  treeinfer amortise --tree tree.yaml --out amortised/tree        # the defaults of `simulate`
  treeinfer amortise --tree tree.yaml --out amortised/tree --n-traj 3 --duration 1 \\
      --simulations 200000 --seed 1                              # on a GPU: minutes
  treeinfer infer --tree tree.yaml --data data/new --out run --amortised amortised/tree

The model is trained for one tree and one layout of recordings: --n-traj pulls of --duration s
sampled every --dt s at --grasp-fraction, down along gravity, with forces of the --profile-kind
family peaking in --peak-range N. `infer --amortised` refuses it (exit 2, naming what differs)
for another tree, another number of pulls, samples, time step or grasp point.

Training noise: sigma_x log-uniform in --noise-displacement-range; the recorded force noise-free
in a quarter of the data sets (as `treeinfer simulate` writes it without --noise-force), else
log-uniform in --noise-force-range. `infer --amortised` checks the flow's answer against the
simulator (importance weights, refined from the flow's best draws by the start pipeline's LM
fit when the flow is too wide) and falls back to the simulator-based path when it fails.

OUT/ holds model.msgpack (the weights, flax msgpack) and model.json (the tree's description and
fingerprint, the layout, the training settings and report, the treeinfer version); it is built
aside and appears whole or not at all. See docs/amortised.md.
"""


def configure_amortise(subparsers) -> argparse.ArgumentParser:
    p = add_command_parser(
        subparsers,
        "amortise",
        help=COMMAND_HELP["amortise"],
        description="Train a neural posterior estimator of the tree's joint stiffness, damping "
        "and displacement noise (a conditional normalizing flow on a learned summary of the "
        "recordings) on simulations drawn from the prior and the noise model, for `treeinfer "
        "infer --amortised`: a new recording's posterior in milliseconds, checked against the "
        "simulator on the spot.",
        epilog=_EPILOG,
    )
    p.add_argument("--tree", required=True, type=Path, help="tree description (YAML/JSON)")
    add_out_option(p, "MODEL")
    p.add_argument(
        "--n-traj",
        type=int,
        default=8,
        metavar="N",
        help="number of pulls (trajectories) per recording (default 8)",
    )
    p.add_argument(
        "--duration", type=float, default=3.0, metavar="S", help="s per pull (default 3)"
    )
    p.add_argument(
        "--dt", type=float, default=0.01, metavar="S", help="s between samples (default 0.01)"
    )
    p.add_argument(
        "--profile-kind",
        choices=SET_KINDS,
        default="mixed",
        help="kind of the random force profiles (default mixed: ramp and "
        "ramp-hold-release alternately)",
    )
    p.add_argument(
        "--peak-range",
        type=_pair,
        default=DEFAULT_PEAK_RANGE,
        metavar="LO,HI",
        help="N, range of the random peaks (default "
        f"{DEFAULT_PEAK_RANGE[0]:g},{DEFAULT_PEAK_RANGE[1]:g})",
    )
    p.add_argument(
        "--grasp-fraction",
        type=float,
        metavar="F",
        help="grasp point along the grasped branch, in (0, 1] (default: the tree's)",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        metavar="S",
        help="seed of the simulations, the network's weights and the training",
    )
    p.add_argument("--force", action="store_true", help="replace a non-empty output folder")
    t = p.add_argument_group("training")
    t.add_argument(
        "--simulations",
        type=int,
        default=20000,
        metavar="N",
        help="simulated data sets to train on (default 20000; 1e5-1e6 on a GPU for "
        "sharp posteriors)",
    )
    t.add_argument(
        "--noise-displacement-range",
        type=_pair,
        default=(1e-4, 5e-3),
        metavar="LO,HI",
        help="m, range of the displacement noise sigma_x drawn "
        "log-uniformly per data set (default 0.0001,0.005)",
    )
    t.add_argument(
        "--noise-force-range",
        type=_pair,
        default=(5e-3, 0.2),
        metavar="LO,HI",
        help="N, range of the recorded force's noise drawn log-uniformly per data "
        "set (default 0.005,0.2)",
    )
    t.add_argument(
        "--epochs",
        type=int,
        default=200,
        metavar="N",
        help="training epochs at most (early stop on a held-out tenth; default 200)",
    )
    t.add_argument(
        "--flow-layers",
        type=int,
        default=5,
        metavar="N",
        help="layers of the masked autoregressive flow (default 5)",
    )
    t.add_argument(
        "--width",
        type=int,
        default=64,
        metavar="N",
        help="hidden units of the networks (default 64)",
    )
    add_backend_option(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def amortise_config(args: argparse.Namespace):
    from ..amortised.config import AmortiseConfig, PullLayout, TrainConfig

    layout = PullLayout(
        args.n_traj,
        args.duration,
        args.dt,
        args.grasp_fraction,
        args.profile_kind,
        tuple(args.peak_range),
    )
    train = TrainConfig(
        simulations=args.simulations,
        flow_layers=args.flow_layers,
        width=args.width,
        epochs=args.epochs,
        seed=args.seed,
        sigma_x_range=tuple(args.noise_displacement_range),
        sigma_f_range=tuple(args.noise_force_range),
        backend=args.backend or "auto",
    )
    return AmortiseConfig(layout, train)


def run_amortise(args: argparse.Namespace) -> int:
    from ..amortised import estimator
    from ..io.atomic import check_output_dir
    from ..tree.description import load_tree

    _prepare_jax()
    cfg = amortise_config(args)  # every option checked before anything is simulated
    check_output_dir(args.out, args.force, "amortised model", inputs=[args.tree])
    tree = load_tree(args.tree)
    if args.grasp_fraction is not None:
        tree = tree.with_grasp(args.grasp_fraction)
    t0 = time.perf_counter()
    am = estimator.train(tree, cfg, log=_say, progress=not args.no_progress)
    estimator.save(am, args.out, args.force, inputs=[args.tree], log=_say)
    tr = am.meta["training"]
    print(
        f"trained on {tr['n_datasets']} simulated data sets ({tr['n_unstable']} unstable "
        f"dropped) in {time.perf_counter() - t0:.0f} s ({tr['simulation_s']:.0f} s simulating, "
        f"{tr['epochs_run']} epochs); held-out loss {tr['best_val_loss']:.3f}"
    )
    print(
        f"wrote {args.out}/ (model.msgpack, model.json) for tree '{tree.name}' "
        f"(fingerprint {am.meta['tree_fingerprint'][:12]})"
    )
    return EXIT_OK


# ---- infer --amortised ------------------------------------------------------------------------
def _refuse_other_sensors(data) -> None:
    """ConfigError (exit 2) for a data folder with observation channels (channels.yaml: other
    sensors) or per-recording pulls (pulls.yaml: other grasp points or directions): a model is
    trained on the grasp point's force and displacement of pulls down at the tree's grasp, and
    its summary has no place for the rest."""
    from ..data.channels import CHANNELS_FILE
    from ..data.pulls import PULLS_FILE

    if data is None:
        return
    for name, what in (
        (CHANNELS_FILE, "observation channels (other sensors)"),
        (PULLS_FILE, "per-recording pulls (other grasp points or directions)"),
    ):
        if (Path(data) / name).exists():
            raise ConfigError(
                f"--data {data}: {name} declares {what}; an amortised model is trained on the "
                "grasp point's force and displacement of pulls down at the tree's grasp only. "
                "Infer without --amortised"
            )


def amortised_for_infer(args: argparse.Namespace, inputs, options: dict):
    """``(start, report)`` for :func:`treeinfer.runs.run_inference` from ``infer --amortised M``:
    the model loaded, refused (ConfigError, exit 2) for another tree or layout or a run whose
    parameters it does not cover, its posterior printed with its latency."""
    from ..amortised import check, estimator

    if options.get("likelihood") != "gaussian" or options.get("noise_displacement") is not None:
        raise ConfigError(
            "--amortised: the model's posterior is over the gains and sigma_x under the Gaussian "
            "noise model; use the default --likelihood gaussian with sigma_x inferred (leave "
            "out --noise-displacement)"
        )
    if options.get("model_kind", "dynamic") != "dynamic" or options.get("tie"):
        raise ConfigError(
            "--amortised: the model is of the dynamic model of every joint's "
            "Kp and Kd; leave out --model-kind static and --tie"
        )
    _refuse_other_sensors(args.data)
    t0 = time.perf_counter()
    am = estimator.load(args.amortised)
    am.check_tree(inputs.tree, f"--tree {args.tree}")
    force, disp = am.check_recordings(
        inputs.trajectories, args.grasp_fraction, f"--data {args.data}"
    )
    load_s = time.perf_counter() - t0
    start, report = check.amortised_start(
        am, force, disp, str(args.amortised), seed=options.get("seed", 0)
    )
    report["load_s"] = round(load_s, 3)
    _say(
        f"amortised posterior from {args.amortised} in {report['latency_ms']:.1f} ms "
        f"({report['latency_cpu_ms']:.1f} CPU-ms; features, summary and {report['n_draws']} "
        f"flow draws; model loaded and checked against the tree and the recordings in "
        f"{1e3 * load_s:.0f} ms); checking it against the simulator"
    )
    for s in report["flow_posterior"]:
        _say(f"  {s['label']:<16} {s['mean']:.4g}  [{s['lower']:.4g}, {s['upper']:.4g}]")
    return start, report
