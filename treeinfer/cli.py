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
    "Command",
    "add_command_parser",
    "build_parser",
    "configure_import_bag",
    "configure_simulate",
    "configure_tree",
    "default_true_params",
    "main",
    "parse_params",
    "run_import_bag",
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
    """Persistent XLA cache: MJX compiles slowly, a second run with the same shapes skips it."""
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
        "profiles using known (or drawn) joint stiffness and damping, in one batched MJX "
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
    p.add_argument("--max-sim-dt", type=float, default=None, help="s, upper bound on the simulation step (default 0.002)")
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

    rollout, sim = _simulate_batch(tree, kp, kd, forces, args.dt, args.max_sim_dt)
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


def _simulate_batch(tree, kp, kd, forces, dt, max_sim_dt):
    """One batched rollout: P = 1 parameter set x B profiles."""
    _prepare_jax()
    import jax

    from .simulator import DEFAULT_MAX_SIM_DT, make_simulator, simulate

    sim = make_simulator(_sim_tree(tree, kp), obs_dt=dt, max_sim_dt=max_sim_dt or DEFAULT_MAX_SIM_DT)
    _say(f"simulating {forces.shape[0]} trajectories (the first run with new shapes compiles for up to a minute; cached afterwards)...")
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

    from .simulator import DEFAULT_MAX_SIM_DT

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
        "simulation": {"substeps": sim.substeps, "sim_dt": sim.sim_dt},
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


# ==== the command table and main ==================================================================
class Command(NamedTuple):
    """A subcommand: ``configure(subparsers) -> parser`` and ``run(args) -> exit code``."""

    configure: Callable[[Any], argparse.ArgumentParser]
    run: Callable[[argparse.Namespace], int | None]


COMMANDS: dict[str, Command] = {
    "tree": Command(configure_tree, run_tree),
    "simulate": Command(configure_simulate, run_simulate),
    "import-bag": Command(configure_import_bag, run_import_bag),
}

_MAIN_EPILOG = """\
a typical sim-to-sim session:
  treeinfer tree --kind fractal --depth 1 --base-pitch 10 --out tree.yaml
  treeinfer simulate --tree tree.yaml --out data --n-traj 8 --seed 1

Run `treeinfer COMMAND --help` for a command's options and examples. Errors in your input are
reported in one line (exit code 2); add --debug to see the traceback.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="treeinfer",
        description=textwrap.fill(
            "Infer the stiffness and damping of tree-branch joints from robot "
            "force-deformation trajectories, with a batched MuJoCo MJX simulator.",
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
