"""The ``treeinfer`` command line.

Each subcommand is a pair ``configure_<name>(subparsers) -> parser`` and ``run_<name>(args) ->
exit code`` registered in :data:`COMMANDS`; to add one, write the pair and add a table entry.
``configure_*`` should create its parser with :func:`add_command_parser` (which adds the shared
``--debug`` and the help formatting) and give it a description and an epilog with an example.

Exit codes: 0 success; 2 a user error (a :class:`~treeinfer.errors.TreeinferError`, a file that
cannot be written, or a bad option: ``error: <message>`` on stderr, no traceback); 3 a bug in
treeinfer (a short message; ``--debug`` shows the traceback); 130 interrupted (Ctrl-C).
"""

from __future__ import annotations

import argparse
import math
import sys
import textwrap
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from . import __version__
from .errors import ConfigError, OutputExistsError, SimulationError, TreeinferError

__all__ = [
    "COMMANDS",
    "INFER_DEFAULTS",
    "Command",
    "add_command_parser",
    "build_parser",
    "configure_demo",
    "configure_evaluate",
    "configure_import_bag",
    "configure_infer",
    "configure_predict",
    "configure_simulate",
    "configure_tree",
    "default_true_params",
    "main",
    "parse_params",
    "run_demo",
    "run_evaluate",
    "run_import_bag",
    "run_infer",
    "run_predict",
    "run_simulate",
    "run_tree",
]

EXIT_OK = 0
EXIT_USER_ERROR = 2
EXIT_INTERNAL_ERROR = 3
EXIT_INTERRUPTED = 130  # the shell's convention for SIGINT (128 + 2)

_WIDTH = 88  # help text width
TREE_SUFFIXES = (".yaml", ".yml", ".json")
# Default true parameters of `simulate`: a log-uniform draw inside this window of each joint's
# log prior box (fractions of its width), away from the edges where the smoothed box prior bites.
TRUE_PARAMS_WINDOW = (1.0 / 3.0, 2.0 / 3.0)


# ---- shared helpers ---------------------------------------------------------------------------
_COMMON = argparse.ArgumentParser(add_help=False)
# SUPPRESS: a subcommand's --debug must not reset a global `treeinfer --debug ...` to False.
_COMMON.add_argument(
    "--debug", action="store_true", default=argparse.SUPPRESS, help="show full tracebacks on errors"
)


class _Formatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Keep the description/epilog layout and show defaults (where they are not None)."""

    def _get_help_string(self, action):
        d = action.default
        if d is None or d is False or d is argparse.SUPPRESS or "%(default)" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


def add_command_parser(subparsers, name: str, help: str, description: str, epilog: str) -> argparse.ArgumentParser:
    """A subcommand parser with the shared options (``--debug``) and help layout."""
    return subparsers.add_parser(
        name,
        help=help,
        description=textwrap.fill(description, width=_WIDTH),
        epilog=epilog,
        parents=[_COMMON],
        formatter_class=_Formatter,
    )


def _floats(text: str) -> list[float]:
    """argparse type: comma-separated numbers, e.g. ``0.5,0.4``."""
    parts = [p for p in text.replace(" ", ",").split(",") if p]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers like '1.0,2.5', got {text!r}") from None
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


def _refuse_existing(paths: Sequence[Path], force: bool) -> None:
    for p in paths:
        if p.exists() and p.is_dir():
            raise OutputExistsError(f"{p}: is a folder, expected a file name")
        if p.exists() and not force:
            raise OutputExistsError(f"{p}: file exists; choose another name or pass --force to replace it")


def _prepare_jax() -> None:
    """Persistent XLA cache: a second run with the same shapes skips compiling (MJX takes a minute)."""
    import treeinfer

    treeinfer.enable_compilation_cache()


def _say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# ==== tree ========================================================================================
_TREE_EPILOG = """\
examples:
  treeinfer tree --kind fractal --depth 2 --branching 2 --base-pitch 20 --out fractal.yaml --mjcf fractal.xml
  treeinfer tree --kind chain --n 3 --lengths 0.7,0.6,0.5 --radii 0.03,0.02,0.014 --out chain.yaml
  treeinfer tree --kind lsystem --axiom F --rule 'F=F[+F]F[-F]' --iterations 2 --angle 25 --out ls.yaml
  treeinfer tree --from two_branch.yaml --grasp-fraction 0.5 --out two_branch.json --urdf two_branch.urdf
  treeinfer tree --from fractal.yaml --kind fractal --depth 3 --out deeper.yaml   # re-generate

Generated trees keep their settings under 'generator:' in the file, so --from FILE --kind KIND
re-generates with only the given options changed. --kind explicit (the default with --from)
converts a tree file as it is (YAML <-> JSON by suffix), applying the grasp/inference options.
"""

# CLI option (argparse dest) -> (generator argument, generator kinds that take it)
_GENERATOR_OPTIONS: dict[str, tuple[str, frozenset[str]]] = {
    "n": ("n", frozenset({"chain"})),
    "lengths": ("lengths", frozenset({"chain"})),
    "radii": ("radii", frozenset({"chain"})),
    "angles": ("angles_deg", frozenset({"chain"})),
    "depth": ("depth", frozenset({"fractal"})),
    "branching": ("branching", frozenset({"fractal"})),
    "length_ratio": ("length_ratio", frozenset({"fractal", "lsystem"})),
    "fork_angles": ("fork_angles_deg", frozenset({"fractal"})),
    "base_length": ("base_length", frozenset({"fractal"})),
    "base_radius": ("base_radius", frozenset({"fractal", "lsystem"})),
    "axiom": ("axiom", frozenset({"lsystem"})),
    "rule": ("rules", frozenset({"lsystem"})),
    "iterations": ("iterations", frozenset({"lsystem"})),
    "angle": ("angle_deg", frozenset({"lsystem"})),
    "step_length": ("step_length", frozenset({"lsystem"})),
    "seed": ("seed", frozenset({"lsystem"})),
    "grasp": ("grasp", frozenset({"fractal", "lsystem", "explicit"})),
    "grasp_fraction": ("grasp_fraction", frozenset({"chain", "fractal", "lsystem", "explicit"})),
    "levels": ("levels", frozenset({"chain", "fractal", "lsystem", "explicit"})),
    "tree_name": ("name", frozenset({"chain", "fractal", "lsystem", "explicit"})),
    "base_position": ("base_position", frozenset({"chain", "fractal", "lsystem", "explicit"})),
    "base_pitch": ("base_pitch_deg", frozenset({"chain", "fractal", "lsystem", "explicit"})),
    "base_yaw": ("base_yaw_deg", frozenset({"chain", "fractal", "lsystem", "explicit"})),
}
_TREE_KINDS = ("explicit", "chain", "fractal", "lsystem")


def configure_tree(subparsers) -> argparse.ArgumentParser:
    p = add_command_parser(
        subparsers,
        "tree",
        help="write a tree description (and MJCF/URDF models) from a generator or a tree file",
        description="Build a tree from a generator (chain, fractal, L-system) or an existing tree "
        "file, write its description (YAML or JSON by the --out suffix) and optionally the MuJoCo "
        "MJCF and URDF models, and print a short summary (branches, inferred joints, grasp).",
        epilog=_TREE_EPILOG,
    )
    p.add_argument("--out", required=True, type=Path, help="tree file to write (.yaml, .yml or .json)")
    p.add_argument("--kind", choices=_TREE_KINDS, help="generator (default: explicit with --from, else fractal)")
    p.add_argument("--from", dest="source", type=Path, metavar="FILE", help="existing tree file to convert or re-generate")
    p.add_argument("--mjcf", type=Path, metavar="FILE", help="also write the MuJoCo MJCF model (.xml)")
    p.add_argument("--urdf", type=Path, metavar="FILE", help="also write the URDF model (.urdf)")
    p.add_argument("--force", action="store_true", help="replace existing output files")

    g = p.add_argument_group("grasp and inference (all kinds)")
    g.add_argument("--name", dest="tree_name", metavar="NAME", help="the tree's name")
    g.add_argument("--grasp", metavar="BRANCH", help="grasped branch (fractal, lsystem, explicit; a chain is grasped at its tip)")
    g.add_argument("--grasp-fraction", type=float, metavar="F", help="where along the grasped branch, in (0, 1]")
    g.add_argument("--levels", type=int, metavar="N", help="inferred joints from the grasped branch up (default: the whole path)")
    g.add_argument("--kp-bounds", type=_pair, metavar="LO,HI", help="prior box of every inferred Kp, N m/rad")
    g.add_argument("--kd-bounds", type=_pair, metavar="LO,HI", help="prior box of every inferred Kd, N m s/rad")
    g.add_argument("--base-position", type=_triple, metavar="X,Y,Z", help="m, where the root branch starts")
    g.add_argument("--base-pitch", type=float, metavar="DEG", help="root elevation above horizontal, deg (90 = vertical)")
    g.add_argument("--base-yaw", type=float, metavar="DEG", help="root heading about the vertical, deg")

    c = p.add_argument_group("chain")
    c.add_argument("--n", type=int, help="number of branches")
    c.add_argument("--lengths", type=_floats, metavar="L[,L...]", help="m, one for all or one per branch (root first)")
    c.add_argument("--radii", type=_floats, metavar="R[,R...]", help="m, one for all or one per branch")
    c.add_argument("--angles", type=_floats, metavar="DEG[,DEG...]", help="fork angles, deg, one for all or one per branch")

    f = p.add_argument_group("fractal")
    f.add_argument("--depth", type=int, help="fork levels (0: one branch)")
    f.add_argument("--branching", type=int, help="children per fork")
    f.add_argument("--length-ratio", type=float, help="child / parent length (lsystem: per bracket depth)")
    f.add_argument("--fork-angles", type=_floats, metavar="DEG,DEG...", help="fork angle of each child, deg")
    f.add_argument("--base-length", type=float, metavar="M", help="root length, m")
    f.add_argument("--base-radius", type=float, metavar="M", help="root radius, m (fractal, lsystem)")

    ls = p.add_argument_group("lsystem")
    ls.add_argument("--axiom", help="start string, e.g. F")
    ls.add_argument(
        "--rule",
        action="append",
        metavar="S=SUCC",
        help="rewrite rule, repeatable, e.g. 'F=FF-[-F+F]'; stochastic: repeat a symbol with "
        "probabilities, 'F=0.5:F[+F]' 'F=0.5:F[-F]'",
    )
    ls.add_argument("--iterations", type=int, help="rewriting passes")
    ls.add_argument("--angle", type=float, metavar="DEG", help="turtle turn angle, deg")
    ls.add_argument("--step-length", type=float, metavar="M", help="length of one F, m")
    ls.add_argument("--seed", type=int, help="seed for stochastic rules")
    return p


def _parse_rules(items: Sequence[str]) -> dict[str, Any]:
    """``['F=FF', 'X=0.5:F[+X]', 'X=0.5:F[-X]']`` -> the rules mapping of ``generators.lsystem``."""
    grouped: dict[str, list[tuple[float | None, str]]] = {}
    for item in items:
        sym, eq, succ = item.partition("=")
        sym = sym.strip()
        if not eq or len(sym) != 1:
            raise ConfigError(f"--rule {item!r}: expected SYMBOL=SUCCESSOR with a one-character symbol, e.g. 'F=FF-[-F+F]'")
        prob: float | None = None
        head, colon, tail = succ.partition(":")
        if colon:
            try:
                prob = float(head)
            except ValueError:
                prob = None  # a ':' inside an ordinary successor
            else:
                succ = tail
        grouped.setdefault(sym, []).append((prob, succ))
    rules: dict[str, Any] = {}
    for sym, alts in grouped.items():
        if len(alts) == 1 and alts[0][0] is None:
            rules[sym] = alts[0][1]
        elif any(pr is None for pr, _ in alts):
            raise ConfigError(
                f"--rule: symbol '{sym}' has {len(alts)} rules; give each a probability, e.g. '{sym}=0.5:...'"
            )
        else:
            rules[sym] = [(pr, s) for pr, s in alts]
    return rules


def _tree_settings(args: argparse.Namespace, kind: str) -> dict[str, Any]:
    """Generator keyword arguments from the options the user gave; refuse ones ``kind`` ignores."""
    from .tree import Bounds

    out: dict[str, Any] = {}
    for dest, (arg, kinds) in _GENERATOR_OPTIONS.items():
        value = getattr(args, dest)
        if value is None:
            continue
        if kind not in kinds:
            flag = "--" + dest.replace("_", "-") if dest != "tree_name" else "--name"
            raise ConfigError(f"{flag} does not apply to --kind {kind} (it is for: {', '.join(sorted(kinds))})")
        if dest == "rule":
            value = _parse_rules(value)
        elif dest in ("lengths", "radii", "angles") and len(value) == 1:
            value = value[0]
        out[arg] = value
    if args.kp_bounds is not None or args.kd_bounds is not None:
        out["bounds"] = Bounds(
            kp=tuple(args.kp_bounds) if args.kp_bounds is not None else Bounds().kp,
            kd=tuple(args.kd_bounds) if args.kd_bounds is not None else Bounds().kd,
        )
    return out


def _read_raw(path: Path) -> dict[str, Any]:
    """The parsed content of a tree file (already validated by ``load_tree``)."""
    import json

    import yaml

    text = path.read_text(encoding="utf-8")
    d = json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    return d if isinstance(d, dict) else {}


def _convert(tree, settings: dict[str, Any], source: Path):
    """Apply grasp/inference/base options to a loaded tree, through its file representation
    so that every value is validated exactly like a tree file."""
    from .tree import tree_from_dict, tree_to_dict

    d = tree_to_dict(tree)
    if "name" in settings:
        d["name"] = settings["name"]
    if "grasp" in settings:
        d["grasp"]["branch"] = settings["grasp"]
    if "grasp_fraction" in settings:
        d["grasp"]["fraction"] = settings["grasp_fraction"]
    for key, fld in (("base_position", "position"), ("base_pitch_deg", "pitch_deg"), ("base_yaw_deg", "yaw_deg")):
        if key in settings:
            d["base"][fld] = list(settings[key]) if key == "base_position" else settings[key]
    first = tree.bounds[tree.inferred[0]]
    if {"grasp", "levels", "bounds"} & set(settings):
        # the inferred joints (or their box) change: one box for all, from --k?-bounds or the first joint
        bd = settings.get("bounds", first)
        d["inference"] = {
            "levels": settings.get("levels", tree.n_inferred),
            "prior": {"kp": list(bd.kp), "kd": list(bd.kd)},
        }
    return tree_from_dict(d, source=str(source))


def _summary(tree, path: Path) -> str:
    from .tree import world_frames

    jointed = sum(not b.fixed for b in tree.branches)
    lines = [
        f"wrote {path}: tree '{tree.name}', {len(tree.branches)} branches ({jointed} jointed), "
        + f"total length {tree.total_length():.3g} m"
    ]
    g = tree.branch(tree.grasp_branch)
    frames = world_frames(tree)
    p0, rot = frames[g.name]
    c = p0 + rot[:, 0] * g.length * tree.grasp_fraction
    lines.append(
        f"  grasp: branch '{g.name}' at fraction {tree.grasp_fraction:.3g} of its length "
        f"({tree.grasp_fraction * g.length:.3g} m from its joint; rest position {np.round(c, 3).tolist()} m)"
    )
    lines.append(f"  inferred joints ({tree.n_inferred}): {', '.join(tree.inferred)}")
    lines.append(f"  parameters: {', '.join(tree.parameter_labels())}")
    boxes = {(tree.bounds[n].kp, tree.bounds[n].kd) for n in tree.inferred}
    if len(boxes) == 1:
        (kp, kd), = boxes
        lines.append(f"  prior box: Kp in [{kp[0]:g}, {kp[1]:g}] N m/rad, Kd in [{kd[0]:g}, {kd[1]:g}] N m s/rad")
    else:
        lines.append("  prior box: per joint (see the file)")
    return "\n".join(lines)


def run_tree(args: argparse.Namespace) -> int:
    import json

    import yaml

    from . import generators as gen
    from ._io import atomic_write_text
    from .export import to_mjcf
    from .tree import load_tree, tree_to_dict
    from .urdf import to_urdf

    out: Path = args.out
    if out.suffix.lower() not in TREE_SUFFIXES:
        raise ConfigError(f"--out {out}: a tree file must end in {', '.join(TREE_SUFFIXES)}")
    kind = args.kind or ("explicit" if args.source is not None else "fractal")
    settings = _tree_settings(args, kind)

    generator_cfg = None  # settings written under generator: (None: a plain tree file)
    if kind == "explicit":
        if args.source is None:
            raise ConfigError("--kind explicit converts a tree file: give it with --from FILE")
        tree = load_tree(args.source)
        raw_gen = _read_raw(args.source).get("generator")
        tree = _convert(tree, settings, args.source) if settings else tree
        if not settings and isinstance(raw_gen, dict):
            generator_cfg = raw_gen  # unchanged tree: its recipe still holds
    else:
        base: dict[str, Any] = {}
        if args.source is not None:
            load_tree(args.source)  # a clear error if the file itself is broken
            raw_gen = _read_raw(args.source).get("generator")
            if not isinstance(raw_gen, dict) or raw_gen.get("kind") != kind:
                found = raw_gen.get("kind") if isinstance(raw_gen, dict) else None
                raise ConfigError(
                    f"--from {args.source}: re-generating with --kind {kind} needs the file's "
                    f"'generator:' settings of kind {kind}, found {found or 'none'}; "
                    "use --kind explicit to convert the tree as it is"
                )
            base = {k: v for k, v in raw_gen.items() if k != "kind"}
        generator_cfg = gen.describe(kind, **{**base, **settings})
        tree = gen.generate(generator_cfg)

    # Build every output in memory first: a failing export leaves no file written.
    mjcf = to_mjcf(tree) if args.mjcf is not None else None
    urdf = to_urdf(tree) if args.urdf is not None else None
    targets = [out] + [p for p in (args.mjcf, args.urdf) if p is not None]
    if len({p.resolve() for p in targets}) != len(targets):
        raise ConfigError("--out, --mjcf and --urdf must name different files")
    _refuse_existing(targets, args.force)

    if generator_cfg is not None and kind != "explicit":
        gen.dump_generated(generator_cfg, out, comment=f"Written by treeinfer {__version__}: treeinfer tree --kind {kind}")
    else:
        d = tree_to_dict(tree)
        if generator_cfg is not None:
            d["generator"] = generator_cfg
        text = json.dumps(d, indent=2) + "\n" if out.suffix.lower() == ".json" else yaml.safe_dump(d, sort_keys=False)
        atomic_write_text(out, text)
    print(_summary(tree, out))
    if mjcf is not None:
        atomic_write_text(args.mjcf, mjcf)
        print(f"wrote {args.mjcf} (MJCF)")
    if urdf is not None:
        atomic_write_text(args.urdf, urdf)
        print(f"wrote {args.urdf} (URDF)")
    return EXIT_OK


# ==== simulate ====================================================================================
_SIMULATE_EPILOG = """\
examples:
  treeinfer simulate --tree two_branch.yaml --out data/train --n-traj 8 --seed 1
  treeinfer simulate --tree two_branch.yaml --out data/test --n-traj 25 --seed 2 \\
      --params-json data/train/true_params.json --noise-force 0.2 --noise-displacement 0.002
  treeinfer simulate --tree two_branch.yaml --out data/one --params 40,80,0.6,1.2 \\
      --profile 'hold:peak=6,ramp=0.5,hold=1.0,release=0.5'

Output folder: traj_000.csv ... (time,force,displacement,velocity in s, N, m, m/s; the velocity
column is the simulator's, left out when displacement noise is added, so that readers
differentiate the noisy displacement as for a recording), tree.yaml (the tree simulated),
true_params.json (the ground truth) and config.json (every option, the seed, the profile
specs and the treeinfer version). Nothing is written unless every trajectory simulates.

True parameters: --params lists Kp of every inferred joint, then Kd, in the tree's label order
(printed by `treeinfer tree --from TREE`); --params-json reads a true_params.json. By default
they are drawn log-uniformly in the middle third of each joint's log prior box with --seed and
ordered so that a parent is at least as stiff and as damped as its child (the inequality
prior's assumption; guaranteed when the joints share one prior box, as by default).

Force profiles (--profile SPEC, repeatable; or a seeded random set of --n-traj, see
--profiles): ramp:peak=N,ramp=S[,start=S]   hold:peak=N,ramp=S,hold=S,release=S[,start=S]
release:peak=N,ramp=S,release=S[,start=S]   step:peak=N,rise=S[,start=S]
"""


def configure_simulate(subparsers) -> argparse.ArgumentParser:
    from .forces import DEFAULT_PEAK_RANGE, SET_KINDS

    p = add_command_parser(
        subparsers,
        "simulate",
        help="simulate synthetic force-deformation trajectories with known parameters",
        description="Sim-to-sim ground truth: pull the tree's grasp point down with a set of force "
        "profiles using known (or drawn) joint stiffness and damping, in one batched "
        "simulation, and write the trajectories in treeinfer's CSV format with the true parameters.",
        epilog=_SIMULATE_EPILOG,
    )
    p.add_argument("--tree", required=True, type=Path, help="tree description (YAML/JSON)")
    p.add_argument("--out", required=True, type=Path, help="output folder (must be empty or absent unless --force)")
    p.add_argument("--n-traj", type=int, default=None, help="number of trajectories (default 8; with --profile: one per spec)")
    p.add_argument("--seed", type=int, default=0, help="seed for the true parameters, profiles and noise")
    gp = p.add_mutually_exclusive_group()
    gp.add_argument("--params", type=_floats, metavar="KP1,..,KPR,KD1,..,KDR", help="true parameters, N m/rad then N m s/rad")
    gp.add_argument("--params-json", type=Path, metavar="FILE", help="true parameters from a true_params.json")
    p.add_argument("--duration", type=float, default=3.0, help="s per trajectory")
    p.add_argument("--dt", type=float, default=0.01, help="s between samples")
    gf = p.add_mutually_exclusive_group()
    gf.add_argument("--profiles", choices=SET_KINDS, default=None, help="kind of random profile set (default mixed: ramp and ramp-hold-release alternately)")
    gf.add_argument("--profile", action="append", metavar="SPEC", help="explicit profile spec, repeatable (one trajectory each)")
    p.add_argument(
        "--peak-range", type=_pair, default=DEFAULT_PEAK_RANGE, metavar="LO,HI", help=f"N, range of the random peaks (default {DEFAULT_PEAK_RANGE[0]:g},{DEFAULT_PEAK_RANGE[1]:g})"
    )
    p.add_argument("--noise-force", type=float, default=0.0, metavar="SIGMA", help="N, Gaussian noise added to the force")
    p.add_argument("--noise-displacement", type=float, default=0.0, metavar="SIGMA", help="m, Gaussian noise added to the displacement")
    p.add_argument("--grasp-fraction", type=float, metavar="F", help="grasp point along the grasped branch, in (0, 1] (default: the tree's)")
    p.add_argument("--max-sim-dt", type=float, default=None, help="s, upper bound on the simulation step (default 0.005)")
    p.add_argument("--backend", choices=("auto", "fused", "mjx"), default="auto", help="simulator: 'fused' (MuJoCo's implicitfast step for hinge trees fused into a few XLA kernels; fast, the default for every tree treeinfer builds), 'mjx' (mujoco.mjx.step) or 'auto' (fused where the model allows, else mjx; default)")
    p.add_argument("--force", action="store_true", help="replace a non-empty output folder")
    return p


def _depth(tree, name: str) -> int:
    return len(tree.ancestors(name))


def default_true_params(tree, rng: np.random.Generator, window: tuple[float, float] = TRUE_PARAMS_WINDOW) -> tuple[np.ndarray, np.ndarray]:
    """Documented default ground truth: (kp [R] N m/rad, kd [R] N m s/rad).

    For Kp and for Kd separately, R fractions ``u`` are drawn uniformly in ``window`` (of the log
    prior box's width), sorted in decreasing order and given to the inferred joints from the
    root-most down (by depth), then mapped into each joint's box: ``lo * (hi / lo) ** u``. So
    every ancestor gets a fraction at least as large as its descendants', and, with one shared
    box, ``parent >= child`` for both Kp and Kd (the inequality prior's assumption).
    """
    lo, hi = tree.bounds_array()
    r = tree.n_inferred
    order = sorted(range(r), key=lambda j: _depth(tree, tree.inferred[j]))  # root-most first
    out = np.empty(2 * r)
    for block in (0, 1):  # Kp, then Kd
        u = np.sort(rng.uniform(window[0], window[1], size=r))[::-1]
        for rank, j in enumerate(order):
            k = block * r + j
            out[k] = lo[k] * (hi[k] / lo[k]) ** u[rank]
    return out[:r], out[r:]


def _check_params(values: Sequence[float], labels: Sequence[str], where: str) -> np.ndarray:
    if len(values) != len(labels):
        raise ConfigError(
            f"{where}: expected {len(labels)} numbers, in the order {', '.join(labels)}; got {len(values)}"
        )
    out = np.empty(len(labels))
    for i, (v, lab) in enumerate(zip(values, labels)):
        try:
            f = float(v)
        except (TypeError, ValueError):
            raise ConfigError(f"{where}: {lab} must be a number, got {v!r}") from None
        if not (math.isfinite(f) and f > 0):
            raise ConfigError(f"{where}: {lab} must be a positive finite number, got {v!r}")
        out[i] = f
    return out


def parse_params(tree, params: Sequence[float] | None = None, params_json: Path | None = None) -> np.ndarray | None:
    """The true parameter vector [2R] (Kp of each inferred joint, then Kd; natural units) from a
    list or a JSON file, or None when neither is given.

    The JSON may be a ``true_params.json`` (``{"kp": {joint: value}, "kd": {joint: value}}``),
    ``{"theta_log": [2R natural logs]}`` or a plain list of 2R numbers."""
    import json

    labels = tree.parameter_labels()
    if params is not None:
        return _check_params(params, labels, "--params")
    if params_json is None:
        return None
    where = f"--params-json {params_json}"
    try:
        d = json.loads(Path(params_json).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{where}: no such file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{where}: cannot read: {e}") from None
    except json.JSONDecodeError as e:
        raise ConfigError(f"{where}, line {e.lineno}: invalid JSON: {e.msg}") from None
    if isinstance(d, list):
        return _check_params(d, labels, where)
    if not isinstance(d, dict):
        raise ConfigError(f"{where}: expected an object with 'kp' and 'kd' (or 'theta_log'), or a list")
    if "kp" in d or "kd" in d:
        vals = []
        for key in ("kp", "kd"):
            m = d.get(key)
            if not isinstance(m, dict):
                raise ConfigError(f"{where}: field '{key}' must map joint names to values, got {m!r}")
            missing = [n for n in tree.inferred if n not in m]
            extra = sorted(set(m) - set(tree.inferred))
            if missing or extra:
                raise ConfigError(
                    f"{where}: field '{key}' must give exactly the inferred joints {list(tree.inferred)}"
                    + (f"; missing {missing}" if missing else "") + (f"; not inferred: {extra}" if extra else "")
                )
            vals += [m[n] for n in tree.inferred]
        return _check_params(vals, labels, where)
    if "theta_log" in d:
        t = d["theta_log"]
        if not isinstance(t, list) or len(t) != len(labels):
            raise ConfigError(f"{where}: field 'theta_log' must be a list of {len(labels)} numbers ({', '.join(labels)})")
        try:
            vals = [math.exp(float(x)) for x in t]
        except (TypeError, ValueError, OverflowError):
            raise ConfigError(f"{where}: field 'theta_log' must hold numbers, got {t!r}") from None
        return _check_params(vals, labels, where)
    raise ConfigError(f"{where}: expected fields 'kp' and 'kd' (or 'theta_log'), found {sorted(d)}")


def _check_simulate_args(args: argparse.Namespace) -> int:
    """Validate the numeric options; returns T."""
    from .forces import n_steps
    from .trajectories import MAX_DT

    for flag, v in (("--dt", args.dt), ("--duration", args.duration)):
        if not (math.isfinite(v) and v > 0):
            raise ConfigError(f"{flag}: must be a positive number of seconds, got {v:g}")
    if args.dt >= MAX_DT:
        raise ConfigError(f"--dt: {args.dt:g} s is too coarse for a pull (must be below {MAX_DT:g} s)")
    if args.n_traj is not None and args.n_traj < 1:
        raise ConfigError(f"--n-traj: must be at least 1, got {args.n_traj}")
    if args.profile and args.n_traj is not None and args.n_traj != len(args.profile):
        raise ConfigError(f"--n-traj {args.n_traj} disagrees with the {len(args.profile)} --profile spec(s) (one trajectory each)")
    for flag, v in (("--noise-force", args.noise_force), ("--noise-displacement", args.noise_displacement)):
        if not (math.isfinite(v) and v >= 0):
            raise ConfigError(f"{flag}: must be >= 0, got {v:g}")
    if args.grasp_fraction is not None and not (0.0 < args.grasp_fraction <= 1.0):
        raise ConfigError(f"--grasp-fraction: must be in (0, 1] (a fraction of the branch length), got {args.grasp_fraction:g}")
    if args.max_sim_dt is not None and not (math.isfinite(args.max_sim_dt) and args.max_sim_dt > 0):
        raise ConfigError(f"--max-sim-dt: must be a positive number of seconds, got {args.max_sim_dt:g}")
    lo, hi = args.peak_range
    if lo > hi:
        raise ConfigError(f"--peak-range: LO must not exceed HI, got {lo:g},{hi:g}")
    try:
        return n_steps(args.duration, args.dt)
    except ConfigError:
        raise ConfigError(
            f"--duration {args.duration:g} s at --dt {args.dt:g} s gives {int(args.duration / args.dt)} "
            "sample(s); at least 3 are needed"
        ) from None


def _sim_tree(tree, kp: np.ndarray):
    """The tree with each Kp prior box widened to contain the true Kp: the simulator picks its
    step from the stiffest corner of the box, so true values above it must still be stable."""
    from .tree import Bounds

    bounds = {
        n: Bounds(kp=(b.kp[0], max(b.kp[1], float(k))), kd=b.kd) for (n, b), k in zip(tree.bounds.items(), kp)
    }
    return replace(tree, bounds=bounds)


def run_simulate(args: argparse.Namespace) -> int:
    from ._io import atomic_write_json, check_output_dir, staged_output_dir
    from .forces import from_spec, random_specs
    from .tree import dump_tree, load_tree

    n_t = _check_simulate_args(args)
    tree = load_tree(args.tree)
    if args.grasp_fraction is not None:
        tree = tree.with_grasp(args.grasp_fraction)
    seq = np.random.SeedSequence(args.seed)  # independent streams: parameters, profiles, noise
    rng_params, rng_profiles, rng_noise = (np.random.default_rng(s) for s in seq.spawn(3))
    theta = parse_params(tree, args.params, args.params_json)
    drawn = theta is None
    if drawn:
        kp, kd = default_true_params(tree, rng_params)
    else:
        kp, kd = theta[: tree.n_inferred], theta[tree.n_inferred :]
    if args.profile:
        specs = list(args.profile)
    else:
        specs = random_specs(args.profiles or "mixed", args.n_traj or 8, args.duration, args.peak_range, rng_profiles)
    forces = np.stack([from_spec(s, args.duration, args.dt) for s in specs])  # [B, T]
    assert forces.shape[1] == n_t
    check_output_dir(args.out, args.force)  # fail before the (slow) simulation

    rollout, sim = _simulate_batch(tree, kp, kd, forces, args.dt, args.max_sim_dt, args.backend)
    names = [f"traj_{i:03d}.csv" for i in range(len(specs))]
    stable = np.asarray(rollout.stable)[0]
    if not stable.all():
        bad = [f"{names[i]} ({specs[i]})" for i in np.flatnonzero(~stable)]
        raise SimulationError(
            f"the simulation blew up for {len(bad)} of {len(specs)} trajectories: {'; '.join(bad)}; "
            f"with {_fmt_params(tree, kp, kd)}: lower the peak forces (--peak-range), the step "
            "(--max-sim-dt) or check the parameters and the tree's units"
        )
    trajs = _trajectories(tree, rollout, forces, args, specs, names, rng_noise)

    labels = tree.parameter_labels()
    true_params = {
        "labels": labels,
        "kp": {n: float(v) for n, v in zip(tree.inferred, kp)},
        "kd": {n: float(v) for n, v in zip(tree.inferred, kd)},
        "theta_log": [float(math.log(v)) for v in np.concatenate([kp, kd])],
        "units": {"kp": "N m/rad", "kd": "N m s/rad", "theta_log": "natural log of kp, kd"},
        "source": "drawn (default_true_params)" if drawn else ("--params" if args.params is not None else str(args.params_json)),
    }
    config = _simulate_config(args, tree, specs, n_t, sim)
    with staged_output_dir(args.out, args.force) as stage:
        from .trajectories import write_trajectory

        for name, (traj, comments) in zip(names, trajs):
            write_trajectory(stage / name, traj, comments)
        dump_tree(tree, stage / "tree.yaml")
        atomic_write_json(stage / "true_params.json", true_params)
        atomic_write_json(stage / "config.json", config)
    print(
        f"simulated {len(specs)} trajectories of {n_t} samples (dt {args.dt:g} s, {sim.substeps} "
        f"simulation step(s) of {sim.sim_dt:.3g} s each) on tree '{tree.name}'"
    )
    print(f"  true parameters: {_fmt_params(tree, kp, kd)}")
    peak = float(np.max(np.abs(np.asarray(rollout.tau))))
    print(f"  largest displacement {peak:.3g} m; wrote {args.out}/ ({names[0]} .. {names[-1]}, tree.yaml, true_params.json, config.json)")
    return EXIT_OK


def _fmt_params(tree, kp, kd) -> str:
    return ", ".join(f"{lab}={v:.4g}" for lab, v in zip(tree.parameter_labels(), np.concatenate([kp, kd])))


def _simulate_batch(tree, kp, kd, forces, dt, max_sim_dt, backend="auto"):
    """One batched rollout: P = 1 parameter set x B profiles."""
    _prepare_jax()
    import jax

    from .sim import DEFAULT_MAX_SIM_DT, make_simulator, simulate

    sim = make_simulator(_sim_tree(tree, kp), obs_dt=dt, max_sim_dt=max_sim_dt or DEFAULT_MAX_SIM_DT, backend=backend)
    slow = " (MJX compiles for up to a minute on new shapes; cached afterwards)" if sim.backend == "mjx" else ""
    _say(f"simulating {forces.shape[0]} trajectories{slow}...")
    run = jax.jit(lambda a, b, f: simulate(sim, a, b, f))
    rollout = run(np.asarray(kp)[None], np.asarray(kd)[None], np.asarray(forces))
    return jax.device_get(rollout), sim


def _trajectories(tree, rollout, forces, args, specs, names, rng_noise):
    """[(Trajectory, comment lines)] validated before anything is written."""
    from .trajectories import Trajectory, add_noise, validate_trajectory

    t = np.arange(forces.shape[1], dtype=float) * args.dt
    out = []
    for i, spec in enumerate(specs):
        tau = np.asarray(rollout.tau[0, i], dtype=float)
        vel = np.asarray(rollout.tau_dot[0, i], dtype=float)
        traj = Trajectory(t, forces[i].copy(), tau, vel, names[i])
        if args.noise_force > 0 or args.noise_displacement > 0:
            traj = add_noise(traj, args.noise_force, args.noise_displacement, rng_noise)
            if args.noise_displacement == 0:  # the clean velocity is still the displacement's
                traj = traj._replace(velocity=vel)
            traj = traj._replace(source=names[i])
        try:
            traj = validate_trajectory(traj)
        except TreeinferError as e:
            raise SimulationError(f"simulated trajectory is implausible: {e}") from None
        comments = [
            f"treeinfer {__version__} simulate: synthetic ground truth",
            f"tree: {tree.name} ({args.tree}); grasp: {tree.grasp_branch} at fraction {tree.grasp_fraction:g}",
            f"profile: {spec}",
            f"noise: force sigma {args.noise_force:g} N, displacement sigma {args.noise_displacement:g} m",
        ]
        out.append((traj, comments))
    return out


def _simulate_config(args, tree, specs, n_t, sim) -> dict[str, Any]:
    import jax
    import mujoco

    from .sim import DEFAULT_MAX_SIM_DT

    options = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if not k.startswith("_")}
    options.pop("debug", None)
    options.update(  # the values actually used
        n_traj=len(specs),
        profiles=None if args.profile else (args.profiles or "mixed"),
        max_sim_dt=args.max_sim_dt or DEFAULT_MAX_SIM_DT,
    )
    return {
        "command": "simulate",
        "treeinfer_version": __version__,
        "jax_version": jax.__version__,
        "mujoco_version": mujoco.__version__,
        "options": options,
        "seed": args.seed,
        "seed_streams": "numpy SeedSequence(seed).spawn(3): true parameters, profiles, noise",
        "tree": tree.name,
        "grasp": {"branch": tree.grasp_branch, "fraction": tree.grasp_fraction},
        "n_steps": n_t,
        "dt": args.dt,
        "profiles": specs,
        "simulation": {"substeps": sim.substeps, "sim_dt": sim.sim_dt, "backend": sim.backend},
    }


# ==== import-bag ==================================================================================
_IMPORT_BAG_EPILOG = """\
examples:
  treeinfer import-bag pulls.bag --out data/real
  treeinfer import-bag rosbag2_folder --out data/real --force-topic /wrench --pose-topic /tf \\
      --tf-child-frame tool0 --force-sign -1

Each pull (force above the rest threshold for at least --min-pull-duration) becomes one
trajectory CSV (time,force,displacement) on a fixed --dt grid, projected on the gravity axis.
"""


def configure_import_bag(subparsers) -> argparse.ArgumentParser:
    from .bags import configure_parser

    p = add_command_parser(
        subparsers,
        "import-bag",
        help="cut a ROS1/ROS2 bag of wrench and pose messages into trajectory CSVs",
        description="Read the force (WrenchStamped) and end-effector pose (PoseStamped, "
        "TransformStamped or /tf) streams from a ROS bag, resample them to a fixed step, project "
        "them on the gravity axis and write one trajectory CSV per pull. No ROS install needed.",
        epilog=_IMPORT_BAG_EPILOG,
    )
    return configure_parser(p)


def run_import_bag(args: argparse.Namespace) -> int:
    from .bags import run_from_args

    run_from_args(args)
    return EXIT_OK


# ==== infer =======================================================================================
# Defaults of `infer` (None in argparse, so that --resume can tell which options were given).
# kT and eta mirror treeinfer.likelihood.DEFAULT_KT and treeinfer.inference.DEFAULT_ETA (a test
# checks they agree; importing them here would load JAX for every `--help`).
INFER_DEFAULTS: dict[str, Any] = {
    "sampler": "nnsvgd",
    "particles": 64,
    "iterations": 200,
    "kT": 0.05,
    "seed": 0,
    "eta": 10.0,
    "max_unstable_share": 0.5,
    "checkpoint_every": 25,
    "backend": "auto",
}
SAMPLER_NAMES = ("nnsvgd", "svgd", "sgld", "sghmc", "mh")
# options a resumed run takes from its checkpoint's config (argparse dest -> flag)
_RUN_OPTIONS = {
    "tree": "--tree", "data": "--data", "out": "--out", "sampler": "--sampler", "particles": "--particles",
    "iterations": "--iterations", "kT": "--kT", "seed": "--seed", "eta": "--eta",
    "grasp_fraction": "--grasp-fraction", "checkpoint_every": "--checkpoint-every", "force": "--force",
    "backend": "--backend",
}

_INFER_EPILOG = """\
examples:
  treeinfer infer --tree two_branch.yaml --data data/train --out runs/nnsvgd
  treeinfer infer --tree two_branch.yaml --data data/train --out runs/mh --sampler mh \\
      --particles 32 --iterations 2000 --seed 3
  treeinfer infer --resume runs/nnsvgd          # continue a killed or interrupted run

Every *.csv in --data is a training trajectory (one time step for all); a true_params.json there
(as `treeinfer simulate` writes) is marked in the pair plot and compared in summary.json.

The run folder (config.json, tree.yaml, posterior.nc, particles.csv, trace.npz, summary.json,
plots/) is built aside and appears complete or not at all. While sampling, RUN.partial/ beside
it holds the config and a checkpoint every --checkpoint-every iterations; after a crash, a kill
or Ctrl-C, `treeinfer infer --resume RUN` continues from the last checkpoint with the recorded
settings (refusing if a data file changed) and gives the same particles as an uninterrupted run.
"""


def configure_infer(subparsers) -> argparse.ArgumentParser:
    d = INFER_DEFAULTS
    p = add_command_parser(
        subparsers,
        "infer",
        help="infer the posterior of the joints' Kp/Kd from training trajectories",
        description="Sample the posterior over the stiffness Kp and damping Kd of the tree's inferred "
        "joints given force-deformation trajectories, with NNSVGD (the default: SVGD with the learned "
        "parent-stiffer-than-child prior), SVGD, SGLD, SGHMC or Metropolis-Hastings, and write a run "
        "folder for `treeinfer predict` and `treeinfer evaluate`. Prints the posterior mean and 95% "
        "interval of every parameter, convergence warnings and the number of unstable particles.",
        epilog=_INFER_EPILOG,
    )
    p.add_argument("--tree", type=Path, help="tree description (YAML/JSON)")
    p.add_argument("--data", type=Path, metavar="DIR", help="folder of training trajectory CSVs")
    p.add_argument("--out", type=Path, metavar="RUN", help="run folder to write (must be empty or absent unless --force)")
    p.add_argument("--sampler", choices=SAMPLER_NAMES, help=f"sampler (default {d['sampler']})")
    p.add_argument("--particles", type=int, metavar="N", help=f"particles (SVGD) or chains (MCMC), >= 2 (default {d['particles']})")
    p.add_argument("--iterations", type=int, metavar="N", help=f"sampler iterations, >= 1 (default {d['iterations']})")
    p.add_argument("--kT", type=float, metavar="X", help=f"likelihood temperature in loss units (m + m/s) per nat; smaller = sharper posterior (default {d['kT']:g})")
    p.add_argument("--seed", type=int, metavar="S", help=f"seed of the initial particles and the sampler (default {d['seed']})")
    p.add_argument("--eta", type=float, metavar="X", help=f"NNSVGD inequality-prior slope, nats per unit of log gain a child exceeds its parent (default {d['eta']:g})")
    p.add_argument("--grasp-fraction", type=float, metavar="F", help="where along the grasped branch the data were recorded, in (0, 1] (default: the tree's grasp)")
    p.add_argument("--max-unstable-share", type=float, metavar="F", help=f"stop with an error if more than this share of the final particles simulate unstably (default {d['max_unstable_share']:g}); may be changed with --resume")
    p.add_argument("--checkpoint-every", type=int, metavar="N", help=f"write RUN.partial/checkpoint.npz every N iterations; 0: only at the end of sampling (default {d['checkpoint_every']})")
    p.add_argument("--resume", type=Path, metavar="RUN", help="continue the interrupted run RUN (all settings come from RUN.partial/config.json)")
    p.add_argument("--force", action="store_true", default=None, help="replace a non-empty RUN (and discard an interrupted RUN.partial)")
    p.add_argument("--backend", choices=("auto", "fused", "mjx"), help="simulator: 'fused' (MuJoCo's implicitfast step for hinge trees fused into a few XLA kernels; fast, the default for every tree treeinfer builds), 'mjx' (mujoco.mjx.step) or 'auto' (fused where the model allows, else mjx; default)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def _check_infer_options(o: dict[str, Any]) -> None:
    """ConfigError naming the flag for any out-of-range option (before anything is read)."""
    def count(flag, v, minimum, why=""):
        if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
            raise ConfigError(f"{flag}: must be an integer >= {minimum}{why}, got {v!r}")

    count("--particles", o["particles"], 2, " (SVGD's kernel needs pairs of particles and a 95% interval needs two)")
    count("--iterations", o["iterations"], 1)
    count("--checkpoint-every", o["checkpoint_every"], 0)
    count("--seed", o["seed"], 0)
    if not (math.isfinite(o["kT"]) and o["kT"] > 0):
        raise ConfigError(f"--kT: must be a positive number (loss units per nat), got {o['kT']:g}")
    if not (math.isfinite(o["eta"]) and o["eta"] > 0):
        raise ConfigError(f"--eta: must be a positive number, got {o['eta']:g}")
    g = o["grasp_fraction"]
    if g is not None and not (math.isfinite(g) and 0.0 < g <= 1.0):
        raise ConfigError(f"--grasp-fraction: must be in (0, 1] (a fraction of the branch length), got {g:g}")
    _check_share(o["max_unstable_share"])


def _check_share(s) -> None:
    if s is not None and not (math.isfinite(s) and 0.0 <= s <= 1.0):
        raise ConfigError(f"--max-unstable-share: must be a fraction in [0, 1], got {s:g}")


def _fmt_gain(v: float) -> str:
    return "nan" if not math.isfinite(v) else f"{v:.4g}"


def _print_posterior(summary: dict) -> None:
    table = summary["posterior"]
    n_unst = summary["n_unstable"]
    print(f"posterior ({summary['n_particles']} particles, {n_unst} unstable, excluded): mean and 95% interval")
    width = max(len(k) for k in table)
    for lab, s in table.items():
        print(f"  {lab:<{width}}  {_fmt_gain(s['mean']):>9} {s['unit']:<10} [{_fmt_gain(s['lower'])}, {_fmt_gain(s['upper'])}]")


def _print_fit(m: dict | None, what: str) -> None:
    if not m:
        return
    print(f"{what}: 95% band {1000 * m['ci_width']:.3g} mm wide on average, {m['pct_outside']:.1f}% of "
          f"points outside it, predictive NLL {m['predictive_nll_per_point']:.3g} nats/point")


def _print_warnings(warns: Sequence[str]) -> None:
    if warns:
        print("convergence warnings:")
        for w in warns:
            print(f"  - {w}")
    else:
        print("convergence: no warnings")


def run_infer(args: argparse.Namespace) -> int:
    from . import runs

    _prepare_jax()
    _check_share(args.max_unstable_share)
    progress = not args.no_progress
    holder: dict[str, Any] = {}
    if args.resume is not None:
        given = [flag for dest, flag in _RUN_OPTIONS.items() if getattr(args, dest) is not None]
        if given:
            raise ConfigError(
                f"--resume takes every setting from {args.resume}{runs.PARTIAL_SUFFIX}/config.json; "
                f"leave out {', '.join(given)} (only --max-unstable-share and --no-progress may be given)"
            )
        run_dir, config = args.resume, None
    else:
        missing = [f for f, v in (("--tree", args.tree), ("--data", args.data), ("--out", args.out)) if v is None]
        if missing:
            raise ConfigError(f"{', '.join(missing)} required (or --resume RUN to continue an interrupted run)")
        o = {k: (getattr(args, k) if getattr(args, k) is not None else v) for k, v in INFER_DEFAULTS.items()}
        o["grasp_fraction"] = args.grasp_fraction
        _check_infer_options(o)
        run_dir = args.out
        config = runs.infer_config(args.tree, args.data, args.out, force=bool(args.force), **o)
        _say(f"{len(config['data']['files'])} training trajectories from {args.data}; sampling with {o['sampler']} "
             f"({o['particles']} particles x {o['iterations']} iterations)")
    try:
        outcome = runs.run_inference(
            config, resume=args.resume, max_unstable_share=args.max_unstable_share, progress=progress, log=_say,
            on_checkpointer=lambda cp: holder.__setitem__("cp", cp),
        )
    except KeyboardInterrupt:
        cp = holder.get("cp")
        if cp is None:
            _say("interrupted before sampling started; nothing to resume")
        elif cp.last_iteration is None:
            _say(f"interrupted before the first checkpoint; `treeinfer infer --resume {run_dir}` starts the "
                 f"same run again from iteration 0 (settings in {runs.partial_dir(run_dir)}/config.json)")
        else:
            _say(f"interrupted; the sampler state after iteration {cp.last_iteration} is kept in {cp.path}.\n"
                 f"continue with:  treeinfer infer --resume {run_dir}")
        return EXIT_INTERRUPTED
    s = outcome.summary
    _print_posterior(s)
    _print_fit(s.get("training_metrics"), "fit to the training data")
    _print_warnings(s["convergence_warnings"])
    print(f"wrote {run_dir}/ (config.json, tree.yaml, posterior.nc, particles.csv, trace.npz, summary.json, plots/)")
    return EXIT_OK


# ==== predict =====================================================================================
_PREDICT_EPILOG = """\
examples:
  treeinfer predict --run runs/nnsvgd --force data/test/traj_000.csv --out pred/t0
  treeinfer predict --run runs/nnsvgd --force pull.csv --grasp-fraction 0.5 --out pred/mid
  treeinfer predict --run runs/nnsvgd --profile 'hold:peak=6,ramp=0.5,hold=1,release=0.5' \\
      --duration 3 --out pred/hold

FORCE.csv is a trajectory CSV (time,force,displacement[,velocity]: its displacement is drawn as
ground truth) or a force profile with only time,force columns; its time step must be the run's.
--profile SPEC samples a profile spec instead (as in `treeinfer simulate --profile`; see its help).
Writes prediction.csv (time, force, mean, lower, upper [, displacement]; s, N, m), prediction.png
and config.json. Particles whose simulation is unstable are left out and counted.
"""


def configure_predict(subparsers) -> argparse.ArgumentParser:
    p = add_command_parser(
        subparsers,
        "predict",
        help="predict the displacement under a force profile, with a 95%% posterior band",
        description="Simulate every posterior particle of a run under a force profile (a CSV or a "
        "profile spec), optionally grasped at another point of the branch, and write the mean "
        "displacement with its 95% predictive band (per-time-step KDE over the particles).",
        epilog=_PREDICT_EPILOG,
    )
    p.add_argument("--run", required=True, type=Path, metavar="RUN", help="run folder written by `treeinfer infer`")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--force", dest="force_file", type=Path, metavar="FORCE.csv", help="force profile or trajectory CSV")
    src.add_argument("--profile", metavar="SPEC", help="force profile spec, e.g. 'ramp:peak=5,ramp=1'")
    p.add_argument("--duration", type=float, metavar="S", help="s, length of a --profile")
    p.add_argument("--dt", type=float, metavar="S", help="s, sample step of a --profile (default: the run's)")
    p.add_argument("--grasp-fraction", type=float, metavar="F", help="where along the grasped branch the force acts, in (0, 1] (default: where the run's training data were recorded)")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder (must be empty or absent unless --overwrite)")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder (--force names the force file here)")
    return p


def _check_grasp(g) -> None:
    if g is not None and not (math.isfinite(g) and 0.0 < g <= 1.0):
        raise ConfigError(f"--grasp-fraction: must be in (0, 1] (a fraction of the branch length), got {g:g}")


def _base_config(command: str, args: argparse.Namespace) -> dict[str, Any]:
    from . import runs

    options = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if not k.startswith("_")}
    options.pop("debug", None)
    return {"command": command, "versions": runs.versions(), "options": options,
            "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


def run_predict(args: argparse.Namespace) -> int:
    from . import runs
    from ._io import atomic_write_text, check_output_dir, staged_output_dir
    from .plots import plot_trajectory_bands, save_figure

    _check_grasp(args.grasp_fraction)
    check_output_dir(args.out, args.overwrite)
    _prepare_jax()
    run = runs.load_run(args.run)
    dt_run = run.sim.obs_dt
    if args.force_file is not None:
        if args.duration is not None or args.dt is not None:
            raise ConfigError("--duration and --dt go with --profile; a force file has its own time column")
        prof = runs.read_force_profile(args.force_file)
        if not math.isclose(prof.dt, dt_run, rel_tol=1e-6):
            raise ConfigError(
                f"{args.force_file}: time step {prof.dt:g} s differs from the run's {dt_run:g} s "
                "(the data it was inferred from); resample the force profile to the run's step"
            )
    else:
        from .forces import from_spec

        if args.duration is None:
            raise ConfigError("--profile needs --duration (seconds)")
        dt = dt_run if args.dt is None else args.dt
        if not math.isclose(dt, dt_run, rel_tol=1e-6):
            raise ConfigError(f"--dt {dt:g} s differs from the run's {dt_run:g} s; leave it out to use the run's step")
        f = from_spec(args.profile, args.duration, dt)
        prof = runs.ForceProfile(np.arange(len(f)) * dt, f, None, args.profile)
    _say(f"simulating {len(run.theta)} particles (the first prediction of a shape compiles for up to a minute)...")
    grasp = args.grasp_fraction if args.grasp_fraction is not None else run.grasp_fraction
    pred = runs.predict_run(run.sim, run.theta, prof.force[None], grasp, run.stable)
    n_bad = int((~pred.valid).sum())
    lower, upper, mean = pred.lower[0], pred.upper[0], pred.mean[0]
    cols = ["time", "force", "mean", "lower", "upper"] + (["displacement"] if prof.displacement is not None else [])
    rows = [prof.time, prof.force, mean, lower, upper] + ([prof.displacement] if prof.displacement is not None else [])
    lines = [
        f"# treeinfer {__version__} predict: run {args.run}, force {prof.source}; s, N, m (positive downward)",
        f"# 95% predictive band over {int(pred.valid.sum())} particles ({n_bad} unstable or invalid, excluded)",
        ",".join(cols),
    ] + [",".join(repr(float(v)) for v in r) for r in zip(*rows)]
    config = _base_config("predict", args)
    config.update(run=str(Path(args.run).resolve()), force_source=prof.source, dt=float(dt_run), n_steps=len(prof.time),
                  grasp_fraction=grasp if grasp is not None else run.tree.grasp_fraction,
                  n_particles=len(run.theta), n_valid=int(pred.valid.sum()), n_excluded=n_bad)
    with staged_output_dir(args.out, args.overwrite) as stage:
        atomic_write_text(stage / "prediction.csv", "\n".join(lines) + "\n")
        fig, _ = plot_trajectory_bands(prof.time, lower, upper, mean, prof.displacement,
                                       samples=pred.tau[pred.valid, 0],
                                       title=f"{prof.source}: 95% band, {int(pred.valid.sum())} particles")
        save_figure(fig, stage / "prediction.png")
        runs.write_json(stage / "config.json", config)
    peak = float(np.max(np.abs(mean)))
    print(f"predicted {len(prof.time)} steps under {prof.source}: peak mean displacement {1000 * peak:.3g} mm, "
          f"band {1000 * float(np.mean(upper - lower)):.3g} mm wide on average; {n_bad} of {len(run.theta)} particles excluded")
    if prof.displacement is not None:
        from .metrics import fraction_outside

        print(f"  {100 * float(fraction_outside(lower, upper, prof.displacement)):.1f}% of the recorded displacement lies outside the band")
    print(f"wrote {args.out}/ (prediction.csv, prediction.png, config.json)")
    return EXIT_OK


# ==== evaluate ====================================================================================
_EVALUATE_EPILOG = """\
examples:
  treeinfer evaluate --run runs/nnsvgd --data data/test --out eval/nnsvgd
  treeinfer evaluate --run runs/nnsvgd --data data/real --kfold 5 --out eval/real-5fold

Writes metrics.json, metrics.md and bands.png (95% predictive bands vs the held-out trajectories)
and config.json. Metrics (treeinfer.metrics.summarize): average 95% band width (m), share of
ground-truth points outside the band (%), predictive NLL of the held-out points under the
per-step KDE, the posterior NLL (particle-averaged kT-scaled loss on the held-out data) and,
if DIR has a true_params.json, the posterior against the true parameters (log space).

--kfold K (the paper's real-to-sim protocol): the trajectories in DIR, in file-name order, are
split into K contiguous folds; for each fold the posterior is inferred afresh on the other K-1
folds with the run's sampler settings (sampler, particles, iterations, kT, eta, seed) and
evaluated on the held-out fold. metrics.json has the per-fold and the mean metrics.
"""


def configure_evaluate(subparsers) -> argparse.ArgumentParser:
    p = add_command_parser(
        subparsers,
        "evaluate",
        help="held-out metrics of a run (or k-fold cross-validation with its settings)",
        description="Score a run's posterior on held-out trajectories: 95% band width, share of "
        "points outside the band, predictive and posterior NLL, posterior vs truth when known; or "
        "cross-validate the run's settings with --kfold.",
        epilog=_EVALUATE_EPILOG,
    )
    p.add_argument("--run", required=True, type=Path, metavar="RUN", help="run folder written by `treeinfer infer`")
    p.add_argument("--data", required=True, type=Path, metavar="DIR", help="folder of held-out trajectory CSVs")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder (must be empty or absent unless --force)")
    p.add_argument("--kfold", type=int, metavar="K", help="k-fold cross-validation over DIR's trajectories (K >= 2)")
    p.add_argument("--grasp-fraction", type=float, metavar="F", help="where along the grasped branch DIR's data were recorded (default: as the run's training data)")
    p.add_argument("--force", action="store_true", help="replace a non-empty output folder")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (--kfold)")
    return p


def _metrics_rows(m: dict) -> list[tuple[str, str]]:
    rows = [
        ("95% band width", f"{1000 * m['ci_width']:.4g} mm"),
        ("ground truth outside the band", f"{m['pct_outside']:.2f} %"),
        ("predictive NLL", f"{m['predictive_nll_per_point']:.4g} nats/point ({m['n_points']} points)"),
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
        out += [f"| {t['name']} | {1000 * t['ci_width']:.4g} | {t['pct_outside']:.2f} |" for t in m["per_trajectory"]]
    if m.get("parameters"):
        out += ["", "| parameter | truth | posterior exp(mean log) | 95% interval | truth inside |", "|---|---|---|---|---|"]
        for lab, p in m["parameters"].items():
            out.append(f"| {lab} | {math.exp(p['truth']):.4g} | {math.exp(p['mean']):.4g} | "
                       f"[{math.exp(p['lower']):.4g}, {math.exp(p['upper']):.4g}] | {'yes' if p['in_interval'] else 'no'} |")
    return out + [""]


def _print_metrics(m: dict, what: str) -> None:
    print(f"{what}:")
    for a, b in _metrics_rows(m):
        print(f"  {a}: {b}")
    if m.get("parameters"):
        inside = sum(p["in_interval"] for p in m["parameters"].values())
        print(f"  true parameters inside their 95% interval: {inside} of {len(m['parameters'])}"
              + ("" if m.get("truth_in_joint_region") is None else
                 f"; inside the joint 95% region: {'yes' if m['truth_in_joint_region'] else 'no'}"))


def _band_arrays(preds_and_obs) -> tuple[np.ndarray, ...]:
    """Stack (prediction, obs) pairs of possibly different lengths into [K, T] arrays (NaN padded)."""
    rows = [(pr.lower[b], pr.upper[b], pr.mean[b], np.where(ob.mask[b], ob.displacement[b], np.nan), ob.mask[b])
            for pr, ob in preds_and_obs for b in range(ob.force.shape[0])]
    t_max = max(len(r[0]) for r in rows)
    out = np.full((5, len(rows), t_max), np.nan)
    for k, r in enumerate(rows):
        for j, a in enumerate(r):
            a = np.where(r[4], a, np.nan) if j < 4 else a
            out[j, k, : len(a)] = a
    return out[0], out[1], out[2], out[3]


def write_evaluation(out: Path, metrics: dict, bands, titles: Sequence[str], dt: float, config: dict, force: bool,
                     md: Sequence[str], extra_files: dict[str, str] | None = None) -> None:
    """metrics.json, metrics.md, bands.png, config.json (+ extra text files) in a staged folder."""
    from . import runs
    from ._io import atomic_write_text, staged_output_dir
    from .plots import plot_band_grid, save_figure

    lower, upper, mean, gt = bands
    with staged_output_dir(out, force) as stage:
        runs.write_json(stage / "metrics.json", metrics)
        atomic_write_text(stage / "metrics.md", "\n".join(md))
        t = np.arange(lower.shape[1]) * dt
        fig, _ = plot_band_grid(t, np.nan_to_num(lower), np.nan_to_num(upper), mean, gt, titles=list(titles),
                                suptitle="95% predictive band vs held-out trajectories")
        save_figure(fig, stage / "bands.png")
        runs.write_json(stage / "config.json", config)
        for name, text in (extra_files or {}).items():
            atomic_write_text(stage / name, text)


def run_evaluate(args: argparse.Namespace) -> int:
    from . import runs
    from ._io import check_output_dir
    from .trajectories import read_trajectory_dir

    _check_grasp(args.grasp_fraction)
    check_output_dir(args.out, args.force)
    _prepare_jax()
    run = runs.load_run(args.run)
    trajs = read_trajectory_dir(args.data)
    dt = trajs[0].dt
    if not math.isclose(dt, run.sim.obs_dt, rel_tol=1e-6):
        raise ConfigError(f"{args.data}: trajectories have dt={dt:g} s but run {args.run} was inferred at "
                          f"dt={run.sim.obs_dt:g} s; resample them to the run's step")
    truth = runs.read_true_params(run.tree, args.data)
    grasp = args.grasp_fraction if args.grasp_fraction is not None else run.grasp_fraction
    config = _base_config("evaluate", args)
    config.update(run=str(Path(args.run).resolve()), data_files=runs.data_manifest(args.data), dt=dt,
                  grasp_fraction=grasp if grasp is not None else run.tree.grasp_fraction, run_options=run.config["options"])
    if args.kfold is None:
        m, pred, obs = runs.evaluate_trajectories(run.sim, run.theta, list(run.labels), trajs, run.kT,
                                                  grasp, truth, run.stable)
        metrics = {"run": str(args.run), "data": str(args.data), "metrics": m}
        md = [f"# treeinfer evaluate: run `{args.run}` on `{args.data}`", ""] + _metrics_md("held-out metrics", m)
        write_evaluation(args.out, metrics, _band_arrays([(pred, obs)]), [t.source for t in trajs], dt, config,
                         args.force, md)
        _print_metrics(m, f"held-out metrics on {len(trajs)} trajectories of {args.data}")
        print(f"wrote {args.out}/ (metrics.json, metrics.md, bands.png, config.json)")
        return EXIT_OK

    runs.kfold_splits(len(trajs), args.kfold)  # K too large: fail before any inference
    o = run.config["options"]
    _say(f"{args.kfold}-fold cross-validation on {len(trajs)} trajectories with the run's settings "
         f"({o['sampler']}, {o['particles']} particles x {o['iterations']} iterations per fold)")
    results = runs.kfold(run.config, run.tree, trajs, args.kfold, grasp, truth,
                         progress=not args.no_progress, log=_say)
    mean, std = runs.mean_metrics([r.metrics for r in results])
    folds = [{"fold": r.fold, "train": r.train, "test": r.test, "metrics": r.metrics} for r in results]
    metrics = {"run": str(args.run), "data": str(args.data), "kfold": args.kfold, "folds": folds, "mean": mean, "std": std}
    md = [f"# treeinfer evaluate --kfold {args.kfold}: settings of `{args.run}` on `{args.data}`", "",
          "| fold | held out | band width [mm] | outside [%] | predictive NLL [nats/point] | posterior NLL |",
          "|---|---|---|---|---|---|"]
    for r in results:
        m = r.metrics
        md.append(f"| {r.fold} | {', '.join(r.test)} | {1000 * m['ci_width']:.4g} | {m['pct_outside']:.2f} | "
                  f"{m['predictive_nll_per_point']:.4g} | {m.get('posterior_nll', float('nan')):.4g} |")
    md.append(f"| mean | | {1000 * mean['ci_width']:.4g} | {mean['pct_outside']:.2f} | "
              f"{mean['predictive_nll_per_point']:.4g} | {(mean.get('posterior_nll') or float('nan')):.4g} |")
    md.append("")
    for r in results:
        md += _metrics_md(f"fold {r.fold} (held out: {', '.join(r.test)})", r.metrics)
    titles = [f"{name} (fold {r.fold})" for r in results for name in r.test]
    # per-fold observations for the band grid
    from .trajectories import stack_trajectories

    by_name = {t.source: t for t in trajs}
    pairs = [(r.prediction, stack_trajectories([by_name[n] for n in r.test])) for r in results]
    labels = list(run.labels)
    extra = {f"fold_{r.fold}_particles.csv": runs.particles_csv(r.theta, labels, np.zeros(len(r.theta)), r.prediction.valid)
             for r in results}
    write_evaluation(args.out, metrics, _band_arrays(pairs), titles, dt, config, args.force, md, extra)
    for r in results:
        _print_metrics(r.metrics, f"fold {r.fold} (held out {', '.join(r.test)})")
    print(f"mean over {args.kfold} folds: 95% band {1000 * mean['ci_width']:.3g} mm, {mean['pct_outside']:.1f}% outside, "
          f"predictive NLL {mean['predictive_nll_per_point']:.3g} nats/point")
    print(f"wrote {args.out}/ (metrics.json, metrics.md, bands.png, config.json, fold_*_particles.csv)")
    return EXIT_OK


# ==== demo ========================================================================================
_DEMO_EPILOG = """\
examples:
  treeinfer demo                       # a few minutes on a laptop CPU
  treeinfer demo --out my-demo --seed 2
  treeinfer demo --quick               # tiny sizes: checks the installation in about a minute

Writes DIR/data/train and DIR/data/test (synthetic trajectories with true_params.json, as
`treeinfer simulate` writes), DIR/run (the run folder of `treeinfer infer`), DIR/evaluation (as
`treeinfer evaluate` writes, on the unseen test trajectories) and DIR/demo.json.
"""


def configure_demo(subparsers) -> argparse.ArgumentParser:
    p = add_command_parser(
        subparsers,
        "demo",
        help="end-to-end example on the built-in 2-branch tree (synthetic data, NNSVGD, metrics)",
        description="Simulate training and unseen test pulls of the built-in two-branch tree with "
        "known stiffness and damping, infer the posterior with NNSVGD, predict the unseen pulls with "
        "95% bands and print how well the bands cover them and how close the posterior is to the truth.",
        epilog=_DEMO_EPILOG,
    )
    p.add_argument("--out", type=Path, default=Path("treeinfer-demo"), metavar="DIR", help="output folder")
    p.add_argument("--quick", action="store_true", help="tiny sizes (seconds of sampling; for tests)")
    p.add_argument("--seed", type=int, default=0, help="seed of the true parameters, the profiles and the sampler")
    p.add_argument("--force", action="store_true", help="replace the contents of a non-empty output folder")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def _write_synthetic(out: Path, tree, trajs, specs, true_params: dict, force: bool, what: str) -> None:
    from ._io import staged_output_dir
    from .trajectories import write_trajectory
    from .tree import dump_tree

    with staged_output_dir(out, force) as stage:
        for tr, spec in zip(trajs, specs):
            write_trajectory(stage / tr.source, tr, [f"treeinfer {__version__} demo: {what}", f"profile: {spec}"])
        dump_tree(tree, stage / "tree.yaml")
        from . import runs

        runs.write_json(stage / "true_params.json", true_params)


def run_demo(args: argparse.Namespace) -> int:
    # Sizes: the whole demo should take about a minute on a 2-core laptop CPU (tune here).
    n_train, n_test = 3, 3  # trajectories (training, unseen test)
    duration, dt = 2.0, 0.02  # s
    particles, iterations = 32, 300
    sampler = "nnsvgd"
    checkpoint_every = 25
    if args.quick:  # tiny: for tests and a first check of an installation
        n_train, n_test, duration, particles, iterations, checkpoint_every = 2, 2, 0.8, 8, 3, 0

    from . import runs
    from ._io import check_output_dir
    from .forces import DEFAULT_PEAK_RANGE, from_spec, random_specs
    from .trajectories import Trajectory, validate_trajectory
    from .tree import load_tree

    if args.seed < 0:
        raise ConfigError(f"--seed: must be >= 0, got {args.seed}")
    out: Path = args.out
    check_output_dir(out, args.force, "demo")
    _prepare_jax()
    tree_file = Path(__file__).resolve().parent / "examples" / "two_branch.yaml"
    tree = load_tree(tree_file)
    rng_params, rng_profiles = (np.random.default_rng(s) for s in np.random.SeedSequence(args.seed).spawn(2))
    kp, kd = default_true_params(tree, rng_params)
    specs = random_specs("mixed", n_train + n_test, duration, DEFAULT_PEAK_RANGE, rng_profiles)
    forces = np.stack([from_spec(s, duration, dt) for s in specs])
    _say(f"demo: simulating {n_train} training and {n_test} unseen test pulls of {duration:g} s on '{tree.name}' "
         f"with {_fmt_params(tree, kp, kd)}")
    rollout, _ = _simulate_batch(tree, kp, kd, forces, dt, None)
    if not np.asarray(rollout.stable).all():
        raise SimulationError("demo: the synthetic pulls blew up; this is a bug in the demo's settings")
    t = np.arange(forces.shape[1]) * dt
    trajs = [validate_trajectory(Trajectory(t, forces[i], np.asarray(rollout.tau[0, i], float),
                                            np.asarray(rollout.tau_dot[0, i], float), f"traj_{i:03d}.csv"))
             for i in range(len(specs))]
    true_params = {
        "labels": tree.parameter_labels(),
        "kp": {n: float(v) for n, v in zip(tree.inferred, kp)},
        "kd": {n: float(v) for n, v in zip(tree.inferred, kd)},
        "theta_log": [float(math.log(v)) for v in np.concatenate([kp, kd])],
        "units": {"kp": "N m/rad", "kd": "N m s/rad"},
        "source": f"demo (default_true_params, seed {args.seed})",
    }
    out.mkdir(parents=True, exist_ok=True)
    data_train, data_test = out / "data" / "train", out / "data" / "test"
    _write_synthetic(data_train, tree, trajs[:n_train], specs[:n_train], true_params, args.force, "training pull")
    _write_synthetic(data_test, tree, trajs[n_train:], specs[n_train:], true_params, args.force, "unseen test pull")

    config = runs.infer_config(
        tree_file, data_train, out / "run", sampler=sampler, particles=particles, iterations=iterations,
        kT=INFER_DEFAULTS["kT"], seed=args.seed, eta=INFER_DEFAULTS["eta"], grasp_fraction=None,
        max_unstable_share=INFER_DEFAULTS["max_unstable_share"], checkpoint_every=checkpoint_every, force=args.force,
    )
    config["via"] = "demo"
    _say(f"demo: {sampler} with {particles} particles x {iterations} iterations")
    outcome = runs.run_inference(config, progress=not args.no_progress, log=_say)
    run = runs.load_run(out / "run")
    truth = np.concatenate([kp, kd])
    test = trajs[n_train:]
    m, pred, obs = runs.evaluate_trajectories(run.sim, run.theta, list(run.labels), test, run.kT, None, truth, run.stable)
    eval_config = _base_config("evaluate", args)
    eval_config.update(run=str((out / "run").resolve()), data_files=runs.data_manifest(data_test), dt=dt, via="demo")
    md = ["# treeinfer demo: NNSVGD posterior on unseen test pulls", ""] + _metrics_md("unseen test trajectories", m)
    write_evaluation(out / "evaluation", {"run": str(out / "run"), "data": str(data_test), "metrics": m},
                     _band_arrays([(pred, obs)]), [tr.source for tr in test], dt, eval_config, args.force, md)
    demo = {
        "sizes": {"n_train": n_train, "n_test": n_test, "duration_s": duration, "dt_s": dt, "particles": particles,
                  "iterations": iterations, "sampler": sampler, "quick": bool(args.quick)},
        "seed": args.seed, "true_params": true_params, "versions": runs.versions(),
        "posterior": outcome.summary["posterior"], "unseen_test_metrics": m,
        "convergence_warnings": outcome.summary["convergence_warnings"],
    }
    runs.write_json(out / "demo.json", demo)

    print(f"true parameters: {_fmt_params(tree, kp, kd)}")
    _print_posterior(outcome.summary)
    _print_metrics(m, f"unseen test trajectories ({n_test})")
    _print_warnings(outcome.summary["convergence_warnings"])
    print(f"wrote {out}/ (data/train, data/test, run/, evaluation/, demo.json); see {out}/run/plots and "
          f"{out}/evaluation/bands.png")
    return EXIT_OK


# ==== the command table and main ==================================================================
class Command(NamedTuple):
    """A subcommand: ``configure(subparsers) -> parser`` and ``run(args) -> exit code``."""

    configure: Callable[[Any], argparse.ArgumentParser]
    run: Callable[[argparse.Namespace], int | None]


COMMANDS: dict[str, Command] = {
    "tree": Command(configure_tree, run_tree),
    "simulate": Command(configure_simulate, run_simulate),
    "import-bag": Command(configure_import_bag, run_import_bag),
    "infer": Command(configure_infer, run_infer),
    "predict": Command(configure_predict, run_predict),
    "evaluate": Command(configure_evaluate, run_evaluate),
    "demo": Command(configure_demo, run_demo),
}

_MAIN_EPILOG = """\
a typical sim-to-sim session:
  treeinfer tree --kind fractal --depth 1 --base-pitch 10 --out tree.yaml
  treeinfer simulate --tree tree.yaml --out data/train --n-traj 8 --seed 1
  treeinfer simulate --tree tree.yaml --out data/test --n-traj 8 --seed 2 \\
      --params-json data/train/true_params.json
  treeinfer infer --tree tree.yaml --data data/train --out run
  treeinfer evaluate --run run --data data/test --out eval
  treeinfer predict --run run --force data/test/traj_000.csv --out pred

or all of it on the built-in example: treeinfer demo

Run `treeinfer COMMAND --help` for a command's options and examples. Errors in your input are
reported in one line (exit code 2); add --debug to see the traceback.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="treeinfer",
        description=textwrap.fill(
            "Infer the stiffness and damping of tree-branch joints from robot "
            "force-deformation trajectories, with a batched MuJoCo simulator in JAX (a fused hinge-tree step, or MJX).",
            width=_WIDTH,
        ),
        epilog=_MAIN_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"treeinfer {__version__}")
    parser.add_argument("--debug", action="store_true", help="show full tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands")
    sub.required = True
    for name, cmd in COMMANDS.items():
        p = cmd.configure(sub)
        if p.prog.split()[-1] != name:  # the table's key is the command's name
            raise RuntimeError(f"COMMANDS['{name}'] configures a parser named '{p.prog}'")
        p.set_defaults(_run=cmd.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit code (see the module docstring)."""
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help, --version, or a usage error (argparse printed it)
        return e.code if isinstance(e.code, int) else (EXIT_OK if e.code is None else EXIT_USER_ERROR)
    debug = bool(getattr(args, "debug", False))
    try:
        rc = args._run(args)
        return EXIT_OK if rc is None else int(rc)
    except TreeinferError as e:
        if debug:
            traceback.print_exc()
        print(f"error: {e}", file=sys.stderr)
        return EXIT_USER_ERROR
    except OSError as e:  # disk full, permission denied, a folder where a file should be...
        if debug:
            traceback.print_exc()
        where = f"{e.filename}: " if e.filename else ""
        print(f"error: {where}{e.strerror or e}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        if debug:
            traceback.print_exc()
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as e:  # noqa: BLE001 -- anything else is a bug: report it, exit 3
        if debug:
            traceback.print_exc()
        print(
            f"internal error ({type(e).__name__}: {e}); this is a bug in treeinfer, please report it "
            "(rerun with --debug for the traceback)",
            file=sys.stderr,
        )
        return EXIT_INTERNAL_ERROR


if __name__ == "__main__":
    sys.exit(main())
