"""What every command shares: exit codes, the parser layout (``add_command_parser``), argparse
types, and the printers of posteriors and metrics.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
import textwrap
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

import treeinfer

from ..errors import ConfigError

EXIT_OK = 0
EXIT_USER_ERROR = 2
EXIT_INTERNAL_ERROR = 3
EXIT_POOR_FIT = 4  # infer: the fit checks judged the run a poor fit (see --allow-poor-fit)
EXIT_INTERRUPTED = 130  # the shell's convention for SIGINT (128 + 2)

_WIDTH = 88  # help text width
TREE_SUFFIXES = (".yaml", ".yml", ".json")

# One line per command for `treeinfer --help` (here, so that it needs no command module).
COMMAND_HELP: dict[str, str] = {
    "tree": "write a tree description (and MJCF/URDF models) from a generator or a tree file",
    "simulate": "simulate synthetic force-deformation trajectories with known parameters",
    "import-bag": "cut a ROS1/ROS2 bag of wrench and pose messages into trajectory CSVs",
    "import-csv": "convert logger CSVs (any columns and units) into trajectory CSVs + pulls.yaml",
    "import-pul": "convert static winch pulling tests (.pul) into force and signed tilts + set-up",
    "infer": "infer the posterior of the joints' Kp/Kd from training trajectories",
    "predict": "predict the displacement under a force profile, with a 95%% posterior band",
    "evaluate": "held-out metrics of a run (or k-fold cross-validation with its settings)",
    "demo": "end-to-end example on the built-in 2-branch tree (synthetic data, NNSVGD, metrics)",
    "suggest": "rank candidate next pulls by expected information gain for a run's posterior",
    "calibrate": "simulation-based calibration: rank histograms, coverage, uniformity test",
    "warmup": "compile the programs of an infer run into the persistent cache, from synthetic data",
    "batch": "infer many trees/branches of a manifest: one run folder each and a results table",
    "amortise": "train a tree's amortised posterior (a flow on simulations) for infer --amortised",
}


# ---- shared helpers ---------------------------------------------------------------------------
_COMMON = argparse.ArgumentParser(add_help=False)
# SUPPRESS: a subcommand's --debug must not reset a global `treeinfer --debug ...` to False.
_COMMON.add_argument(
    "--debug", action="store_true", default=argparse.SUPPRESS, help="show full tracebacks on errors"
)


class _Formatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Keep the description/epilog layout and show defaults (where they are not None); a fixed
    width so that --help reads the same in any terminal (and its line budget can be tested)."""

    def __init__(self, prog, indent_increment=2, max_help_position=30, width=_WIDTH):
        super().__init__(prog, indent_increment, max_help_position, width)

    def _format_args(self, action, default_metavar):
        if getattr(action, "shown_as_flag", False):  # predict's --force (cli.options)
            return ""
        return super()._format_args(action, default_metavar)

    def _format_action_invocation(self, action):
        if getattr(action, "shown_as_flag", False):
            return ", ".join(action.option_strings)
        return super()._format_action_invocation(action)

    def _get_help_string(self, action):
        d = action.default
        if d is None or d is False or d is argparse.SUPPRESS or "%(default)" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


def add_command_parser(
    subparsers, name: str, help: str, description: str, epilog: str
) -> argparse.ArgumentParser:
    """A subcommand parser with the shared options (``--debug``) and help layout."""
    return subparsers.add_parser(
        name,
        help=help,
        description=textwrap.fill(description, width=_WIDTH),
        epilog=epilog,
        parents=[_COMMON],
        formatter_class=_Formatter,
    )


EXPERT_HEADING = "expert options"

# What `treeinfer COMMAND --help` shows first, per command: the options of the everyday job; the
# rest go under EXPERT_HEADING (see group_options). Every option keeps working either way.
COMMON_OPTIONS: dict[str, tuple[str, ...]] = {
    "tree": ("--out", "--kind", "--from", "--model", "--grasp-branch", "--grasp-fraction",
             "--levels", "--kp-bounds", "--kd-bounds", "--mjcf", "--urdf", "--force"),
    "simulate": ("--tree", "--out", "--n-traj", "--seed", "--params", "--params-json",
                 "--duration", "--dt", "--profile-kind", "--noise-displacement", "--noise-force",
                 "--force"),
    "import-bag": ("--out", "--force-topic", "--pose-topic", "--direction", "--grasp-branch",
                   "--grasp-fraction", "--grasp-distance", "--force"),
    "import-csv": ("--out", "--time-column", "--force-column", "--displacement-column",
                   "--units", "--dt", "--tare", "--trim", "--grasp-branch", "--grasp-fraction",
                   "--grasp-distance", "--direction", "--force"),
    "import-pul": ("--out", "--trees", "--force"),
    "infer": ("--tree", "--data", "--out", "--likelihood", "--noise-displacement", "--sampler",
              "--particles", "--iterations", "--seed", "--resume", "--force", "--allow-poor-fit"),
    "predict": ("--run", "--force-csv", "--profile", "--duration", "--dt", "--grasp-fraction",
                "--out", "--force"),
    "evaluate": ("--run", "--data", "--out", "--kfold", "--grasp-fraction", "--force"),
    "demo": ("--out", "--quick", "--seed", "--likelihood", "--force"),
    "suggest": ("--run", "--out", "--grasp-fractions", "--peak-forces", "--target",
                "--parameter", "--top", "--force"),
    "calibrate": ("--tree", "--out", "--datasets", "--likelihood", "--noise-displacement",
                  "--noise-force", "--sampler", "--particles", "--iterations", "--n-traj",
                  "--seed", "--force"),
    "warmup": ("--tree", "--n-traj", "--steps", "--dt"),
    "batch": ("--manifest", "--out", "--workers", "--ray", "--force", "--check"),
    "amortise": ("--tree", "--out", "--n-traj", "--duration", "--dt", "--simulations", "--seed",
                 "--force"),
}  # fmt: skip


def group_options(p: argparse.ArgumentParser, common: Sequence[str]) -> argparse.ArgumentParser:
    """Show the options named in ``common`` first ("common options") and every other option
    under the ``expert options`` heading, with a usage line that lists only the common ones.

    Why after the fact rather than ``add_argument_group`` at each call: the commands' option
    definitions (and the shared ``add_*_options`` helpers) stay exactly as they are, so parsing,
    defaults and option names cannot change, and one list per command says what a newcomer sees
    first. It moves actions between argparse's groups (``_group_actions``, the attribute argparse
    has used for this since Python 3.2); tests/test_cli_help.py checks the result for every
    command, so a change in argparse shows there."""
    wanted = set(common)
    known = {s for a in p._actions for s in a.option_strings}
    unknown = wanted - known
    if unknown:  # a typo here would silently demote an option
        raise ValueError(f"{p.prog}: no such options {sorted(unknown)}")
    optionals = p._optionals
    optionals.title = "common options"
    expert = p.add_argument_group(EXPERT_HEADING)
    for action in list(optionals._group_actions):
        if action.option_strings and not wanted & set(action.option_strings):
            if "-h" in action.option_strings or "--debug" in action.option_strings:
                continue  # -h and --debug stay with the common options
            optionals._group_actions.remove(action)
            expert._group_actions.append(action)
    shown = [a for a in p._actions if not a.option_strings or wanted & set(a.option_strings)]
    formatter = p._get_formatter()
    formatter.add_usage(None, shown, [])
    usage = formatter.format_help().strip().removeprefix("usage:").strip()
    usage = re.sub(r"(--[\w-]+) \]", r"\1]", usage)  # a flag-like option (predict's --force)
    p.usage = usage.replace("%", "%%") + " [expert options]"
    return p


def _floats(text: str) -> list[float]:
    """argparse type: comma-separated numbers, e.g. ``0.5,0.4``."""
    parts = [p for p in text.replace(" ", ",").split(",") if p]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers like '1.0,2.5', got {text!r}"
        ) from None
    if not vals:
        raise argparse.ArgumentTypeError(f"expected at least one number, got {text!r}")
    if not all(math.isfinite(v) for v in vals):
        raise argparse.ArgumentTypeError(f"numbers must be finite, got {text!r}")
    return vals


def _pair(text: str) -> tuple[float, float]:
    """argparse type: two comma-separated numbers ``LO,HI``."""
    vals = _floats(text)
    if len(vals) != 2:
        raise argparse.ArgumentTypeError(f"expected two numbers LO,HI, got {text!r}")
    return (vals[0], vals[1])


def _triple(text: str) -> tuple[float, float, float]:
    vals = _floats(text)
    if len(vals) != 3:
        raise argparse.ArgumentTypeError(f"expected three numbers X,Y,Z, got {text!r}")
    return (vals[0], vals[1], vals[2])


def _prepare_jax() -> None:
    """Persistent XLA cache: a second run with the same shapes skips compiling.

    (MJX takes a minute to compile.)"""
    treeinfer.enable_compilation_cache()


def _say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# ---- shared printers and checks ---------------------------------------------------------------
def _fmt_params(tree, kp, kd) -> str:
    return ", ".join(
        f"{lab}={v:.4g}" for lab, v in zip(tree.parameter_labels(), np.concatenate([kp, kd]))
    )


def _check_share(s) -> None:
    if s is not None and not (math.isfinite(s) and 0.0 <= s <= 1.0):
        raise ConfigError(f"--max-unstable-share: must be a fraction in [0, 1], got {s:g}")


def _fmt_gain(v: float) -> str:
    return "nan" if not math.isfinite(v) else f"{v:.4g}"


def _print_posterior(summary: dict) -> None:
    table = summary["posterior"]
    n_unst = summary["n_unstable"]
    print(
        f"posterior ({summary['n_particles']} particles, {n_unst} unstable, excluded): mean and "
        "95% interval"
    )
    width = max(len(k) for k in table)
    for lab, s in table.items():
        print(
            f"  {lab:<{width}}  {_fmt_gain(s['mean']):>9} {s['unit']:<10} "
            f"[{_fmt_gain(s['lower'])}, {_fmt_gain(s['upper'])}]"
        )


def _print_fit(m: dict | None, what: str) -> None:
    if not m:
        return
    print(
        f"{what}: 95% band {1000 * m['ci_width']:.3g} mm wide on average, "
        f"{m['pct_outside']:.1f}% of points outside it, predictive NLL "
        f"{m['predictive_nll_per_point']:.3g} nats/point"
    )


def _print_warnings(warns: Sequence[str]) -> None:
    if warns:
        print("convergence warnings:")
        for w in warns:
            print(f"  - {w}")
    else:
        print("convergence: no warnings")


def _check_grasp(g) -> None:
    if g is not None and not (math.isfinite(g) and 0.0 < g <= 1.0):
        raise ConfigError(
            f"--grasp-fraction: must be in (0, 1] (a fraction of the branch length), got {g:g}"
        )


def _base_config(command: str, args: argparse.Namespace) -> dict[str, Any]:
    from ..runs import versions  # here, not at the top: `treeinfer --help` must not load JAX

    options = {
        k: (str(v) if isinstance(v, Path) else v)
        for k, v in vars(args).items()
        if not k.startswith("_")
    }
    options.pop("debug", None)
    return {
        "command": command,
        "versions": versions(),
        "options": options,
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def _metrics_rows(m: dict) -> list[tuple[str, str]]:
    rows = [
        ("95% band width", f"{1000 * m['ci_width']:.4g} mm"),
        ("recorded points outside the band", f"{m['pct_outside']:.2f} %"),
        (
            "predictive NLL",
            f"{m['predictive_nll_per_point']:.4g} nats/point ({m['n_points']} points)",
        ),
    ]
    if m.get("posterior_nll") is not None:
        rows.append(("posterior NLL", f"{m['posterior_nll']:.4g} nats"))
    rows.append(("particles used", f"{m['n_valid_particles']} of {m['n_particles']}"))
    return rows


def _metrics_md(title: str, m: dict) -> list[str]:
    out = [f"## {title}", "", "| metric | value |", "|---|---|"]
    out += [f"| {a} | {b} |" for a, b in _metrics_rows(m)]
    if m.get("per_trajectory"):
        out += ["", "| trajectory | band width [mm] | outside [%] |", "|---|---|---|"]
        out += [
            f"| {t['name']} | {1000 * t['ci_width']:.4g} | {t['pct_outside']:.2f} |"
            for t in m["per_trajectory"]
        ]
    if m.get("parameters"):
        out += [
            "",
            "| parameter | truth | posterior exp(mean log) | 95% interval | truth inside |",
            "|---|---|---|---|---|",
        ]
        for lab, p in m["parameters"].items():
            out.append(
                f"| {lab} | {math.exp(p['truth']):.4g} | {math.exp(p['mean']):.4g} | "
                f"[{math.exp(p['lower']):.4g}, {math.exp(p['upper']):.4g}] | "
                f"{'yes' if p['in_interval'] else 'no'} |"
            )
    return out + [""]


def _print_metrics(m: dict, what: str) -> None:
    print(f"{what}:")
    for a, b in _metrics_rows(m):
        print(f"  {a}: {b}")
    if m.get("parameters"):
        inside = sum(p["in_interval"] for p in m["parameters"].values())
        print(
            f"  true parameters inside their 95% interval: {inside} of {len(m['parameters'])}"
            + (
                ""
                if m.get("truth_in_joint_region") is None
                else "; inside the joint 95% region: "
                f"{'yes' if m['truth_in_joint_region'] else 'no'}"
            )
        )


def add_run_option(p: argparse.ArgumentParser) -> None:
    """``--run RUN``: the run folder a command reads; one definition for every command."""
    p.add_argument(
        "--run",
        required=True,
        type=Path,
        metavar="RUN",
        help="run folder written by `treeinfer infer`",
    )


def add_out_option(p: argparse.ArgumentParser, metavar: str = "DIR") -> None:
    """``--out DIR``: the output folder a command writes (replaced only with ``--force``); one
    definition for every command that writes a folder of results."""
    p.add_argument(
        "--out",
        required=True,
        type=Path,
        metavar=metavar,
        help="output folder (must be empty or absent unless --force)",
    )


def add_grasp_point_options(p: argparse.ArgumentParser) -> None:
    """``--grasp-branch``, then ``--grasp-fraction`` or ``--grasp-distance``: where the imported
    recordings were grasped, written to the data folder's ``pulls.yaml`` (the importers)."""
    p.add_argument("--grasp-branch", metavar="NAME", help="grasped branch (pulls.yaml)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--grasp-fraction", type=float, metavar="F", help="grasp point, (0, 1]")
    g.add_argument("--grasp-distance", type=float, metavar="M", help="m from the branch's joint")


BACKEND_HELP = (
    "simulator: 'auto' (pallas on a GPU, else fused, where the model allows; else mjx), "
    "'fused' (MuJoCo's implicitfast hinge-tree step as fused XLA), 'pallas' (one GPU kernel) "
    "or 'mjx'"
)


def add_backend_option(p: argparse.ArgumentParser, default: str | None = "auto") -> None:
    """``--backend``: one definition for every command that simulates."""
    p.add_argument(
        "--backend", choices=("auto", "fused", "mjx", "pallas"), default=default, help=BACKEND_HELP
    )


def add_simulation_options(p: argparse.ArgumentParser, default_note: str = "") -> None:
    """``--force-interp``, ``--max-sim-dt`` and ``--sim-tolerance`` (defaults None: the
    simulator's, or a run's recorded settings where ``default_note`` says so)."""
    p.add_argument(
        "--force-interp",
        choices=("linear", "hold"),
        default=None,
        help="force between samples: 'linear' (default) or 'hold' (each sample held until the "
        "next)" + default_note,
    )
    p.add_argument(
        "--max-sim-dt",
        type=float,
        default=None,
        metavar="S",
        help="s, upper bound on the simulation step (default 0.005)" + default_note,
    )
    p.add_argument(
        "--sim-tolerance",
        type=float,
        default=None,
        metavar="M",
        help="m, accuracy target of the simulated displacement; the step is refined until its "
        "estimated error is below it (default 1e-4; infer with a generative likelihood: a "
        "tenth of the displacement noise, within 1e-4 to 1e-3)" + default_note,
    )


def check_simulation_options(args: argparse.Namespace) -> None:
    """ConfigError naming the flag for a non-positive --max-sim-dt or --sim-tolerance."""
    for flag, v in (("--max-sim-dt", args.max_sim_dt), ("--sim-tolerance", args.sim_tolerance)):
        if v is not None and not (math.isfinite(v) and v > 0):
            raise ConfigError(f"{flag}: must be a positive number, got {v:g}")


def _print_simulation(sim_summary: dict | None) -> None:
    """The chosen simulation step and its estimated error (summary.json's ``simulation``)."""
    if not sim_summary:
        return
    s = sim_summary
    line = (
        f"simulation: forces {s['force_interp']} between samples, {s['substeps']} substeps of "
        f"{s['sim_dt_s'] * 1e3:.3g} ms"
    )
    if s.get("estimated_error_m") is not None:
        line += (
            f", estimated displacement error {s['estimated_error_m'] * 1e3:.3g} mm "
            f"(tolerance {s['sim_tolerance_m'] * 1e3:.3g} mm)"
        )
    _say(line)


_RUN_SIM_NOTE = "; default: the run's recorded simulator"


def simulator_for_run(run, args: argparse.Namespace, forces, grasp_fraction, cache):
    """The run's recorded simulator, or, when --force-interp, --max-sim-dt or --sim-tolerance
    is given, one with those settings whose step is accuracy-controlled on ``forces`` [B, T]."""
    from .. import runs

    check_simulation_options(args)
    if args.force_interp is None and args.max_sim_dt is None and args.sim_tolerance is None:
        return run.sim
    return runs.simulator_for(
        run.tree,
        run.sim.obs_dt,
        None,
        run.sim.backend,
        cache,
        force_interp=args.force_interp or run.sim.force_interp,
        max_sim_dt=args.max_sim_dt,
        sim_tolerance=args.sim_tolerance,
        forces=np.asarray(forces, float),
        grasp_fraction=grasp_fraction,
    )


def add_model_options(p: argparse.ArgumentParser, run: bool = False) -> None:
    """``--model FILE`` (a user's own URDF/MJCF) and, for new trees/runs, ``--repair-inertia``."""
    if run:
        p.add_argument(
            "--model",
            type=Path,
            metavar="FILE",
            help="where the run's own URDF/MJCF model lies now, if it moved (same sha256)",
        )
        return
    p.add_argument(
        "--model",
        type=Path,
        metavar="FILE",
        help="simulate your own URDF (.urdf) or MJCF (.xml) model instead of the tree's "
        "cylinders (the tree file's model: section maps branches to joints and links)",
    )
    p.add_argument(
        "--repair-inertia",
        choices=("geometry", "floor"),
        default=None,
        help="repair links with zero or non-positive-definite inertia: 'geometry' (a solid "
        "cylinder of the link's geom) or 'floor' (a 1 cm radius of gyration); reported",
    )


def print_model_report(report: dict | None) -> None:
    """What was matched, set and repaired in a user model (stderr)."""
    if report:
        from ..tree.usermodel import describe_report

        for line in describe_report(report):
            _say(line)
