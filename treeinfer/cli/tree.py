"""``treeinfer tree``: write, generate or convert a tree description (and its MJCF/URDF)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from .common import (
    COMMAND_HELP,
    _floats,
    _pair,
    _triple,
    add_command_parser,
    add_model_options,
)
from .options import add_deprecated
from .tree_build import _GENERATOR_OPTIONS, _NO_TIE_SCALE  # noqa: F401
from .tree_build import run_tree as _run_tree_build
from .tree_qsm import QSM_EPILOG, add_qsm_options, run_tree_qsm


def run_tree(args: argparse.Namespace) -> int:
    """The command table's entry: ``--from-qsm`` converts a QSM, anything else builds as before."""
    if getattr(args, "from_qsm", None) is not None:
        return run_tree_qsm(args)
    return _run_tree_build(args)


# ==== tree ========================================================================================
_TREE_EPILOG = """\
examples:
  treeinfer tree --kind fractal --depth 2 --branching 2 --base-pitch 20 --out fractal.yaml \\
      --mjcf fractal.xml
  treeinfer tree --kind chain --n 3 --lengths 0.7,0.6,0.5 --radii 0.03,0.02,0.014 --out chain.yaml
  treeinfer tree --kind lsystem --axiom F --rule 'F=F[+F]F[-F]' --lsystem-iterations 2 \\
      --angle 25 --out ls.yaml
  treeinfer tree --from two_branch.yaml --grasp-fraction 0.5 --out two_branch.json \\
      --urdf two_branch.urdf
  treeinfer tree --from fractal.yaml --kind fractal --depth 3 --out deeper.yaml   # re-generate
  treeinfer tree --model my_tree.urdf --grasp-branch link_7 --levels 2 --out t.yaml  # your model
  treeinfer tree --from my_tree.yaml --model my_tree.urdf --repair-inertia geometry --out t.yaml
  treeinfer tree --kind stem --stem-height 0.4 --base-diameter 0.010 --tip-diameter 0.006 \
      --push-heights 0.12,0.24,0.36 --out stem.yaml
  treeinfer tree --kind stem --stem-height 0.4 --base-diameter 0.010 --tip-diameter 0.006 \
      --push-heights-from data/stem --out stem.yaml   # heights from data/stem/pulls.yaml

--model FILE describes your own URDF/MJCF (one branch per link, joint names mapped under
model:) or, with --from, attaches it to a tree file; the model is checked (names, inertias,
joint limits, grasp axis) and the file's sha256 recorded.

--kind stem writes the chain for a stem pushed at a few heights (issue 13's quasi-static
pushes): one hinge per push height at the pseudo-rigid-body pivot, the stiffnesses tied to the
shape that matches the tapered beam at every push height (inference: {tie: shape, tie_shape,
tie_scale}), stiffness only; it prints, per push height, the --grasp-branch/--grasp-distance
that import-csv needs. With --push-heights-from DIR the heights are the 'distance' entries of
DIR/pulls.yaml (import-csv ... --grasp-branch stem --grasp-distance H, H in m above the ground),
and DIR/pulls.yaml is rewritten to point at the chain's links (the original kept as
pulls.yaml.orig).

Generated trees keep their settings under 'generator:' in the file, so --from FILE --kind KIND
re-generates with only the given options changed. --kind explicit (the default with --from)
converts a tree file as it is (YAML <-> JSON by suffix), applying the grasp/inference options.
"""

# CLI option (argparse dest) -> (generator argument, generator kinds that take it)
_TREE_KINDS = ("explicit", "chain", "fractal", "lsystem", "stem")


def configure_tree(subparsers) -> argparse.ArgumentParser:
    p = add_command_parser(
        subparsers,
        "tree",
        help=COMMAND_HELP["tree"],
        description="Build a tree from a generator (chain, fractal, L-system) or an existing tree "
        "file, write its description (YAML or JSON by the --out suffix) and optionally the MuJoCo "
        "MJCF and URDF models, and print a short summary (branches, inferred joints, grasp).",
        epilog=_TREE_EPILOG + "\n" + QSM_EPILOG,
    )
    p.add_argument(
        "--out", required=True, type=Path, help="tree file to write (.yaml, .yml or .json)"
    )
    p.add_argument(
        "--kind",
        choices=_TREE_KINDS,
        help="generator (default: explicit with --from, else fractal)",
    )
    p.add_argument(
        "--from",
        dest="source",
        type=Path,
        metavar="FILE",
        help="existing tree file to convert or re-generate",
    )
    p.add_argument(
        "--mjcf", type=Path, metavar="FILE", help="also write the MuJoCo MJCF model (.xml)"
    )
    p.add_argument("--urdf", type=Path, metavar="FILE", help="also write the URDF model (.urdf)")
    p.add_argument("--force", action="store_true", help="replace existing output files")
    add_model_options(p)

    g = p.add_argument_group("grasp and inference (all kinds)")
    g.add_argument("--name", dest="tree_name", metavar="NAME", help="the tree's name")
    g.add_argument(
        "--grasp-branch",
        dest="grasp",
        metavar="NAME",
        help="grasped branch (fractal, lsystem, explicit; a chain is grasped at its tip)",
    )
    g.add_argument(
        "--grasp-fraction",
        type=float,
        metavar="F",
        help="where along the grasped branch, in (0, 1]",
    )
    g.add_argument(
        "--levels",
        type=int,
        metavar="N",
        help="inferred joints from the grasped branch up (default: the whole path)",
    )
    g.add_argument(
        "--kp-bounds", type=_pair, metavar="LO,HI", help="prior box of every inferred Kp, N m/rad"
    )
    g.add_argument(
        "--kd-bounds", type=_pair, metavar="LO,HI", help="prior box of every inferred Kd, N m s/rad"
    )
    g.add_argument(
        "--base-position", type=_triple, metavar="X,Y,Z", help="m, where the root branch starts"
    )
    g.add_argument(
        "--base-pitch",
        type=float,
        metavar="DEG",
        help="root elevation above horizontal, deg (90 = vertical)",
    )
    g.add_argument(
        "--base-yaw", type=float, metavar="DEG", help="root heading about the vertical, deg"
    )

    c = p.add_argument_group("chain")
    c.add_argument("--n", type=int, help="number of branches")
    c.add_argument(
        "--lengths",
        type=_floats,
        metavar="L[,L...]",
        help="m, one for all or one per branch (root first)",
    )
    c.add_argument(
        "--radii", type=_floats, metavar="R[,R...]", help="m, one for all or one per branch"
    )
    c.add_argument(
        "--angles",
        type=_floats,
        metavar="DEG[,DEG...]",
        help="fork angles, deg, one for all or one per branch",
    )

    f = p.add_argument_group("fractal")
    f.add_argument("--depth", type=int, help="fork levels (0: one branch)")
    f.add_argument("--branching", type=int, help="children per fork")
    f.add_argument(
        "--length-ratio", type=float, help="child / parent length (lsystem: per bracket depth)"
    )
    f.add_argument(
        "--fork-angles", type=_floats, metavar="DEG,DEG...", help="fork angle of each child, deg"
    )
    f.add_argument("--base-length", type=float, metavar="M", help="root length, m")
    f.add_argument(
        "--base-radius", type=float, metavar="M", help="root radius, m (fractal, lsystem)"
    )

    ls = p.add_argument_group("lsystem")
    ls.add_argument("--axiom", help="start string, e.g. F")
    ls.add_argument(
        "--rule",
        action="append",
        metavar="S=SUCC",
        help="rewrite rule, repeatable, e.g. 'F=FF-[-F+F]'; stochastic: repeat a symbol with "
        "probabilities, 'F=0.5:F[+F]' 'F=0.5:F[-F]'",
    )
    ls.add_argument(
        "--lsystem-iterations", dest="iterations", type=int, metavar="N", help="rewriting passes"
    )
    ls.add_argument("--angle", type=float, metavar="DEG", help="turtle turn angle, deg")
    ls.add_argument("--step-length", type=float, metavar="M", help="length of one F, m")
    ls.add_argument("--seed", type=int, help="seed for stochastic rules")

    st = p.add_argument_group("stem (a stem pushed sideways at a few heights)")
    st.add_argument("--stem-height", type=float, metavar="M", help="m, ground (clamp) to tip")
    st.add_argument(
        "--push-heights",
        type=_floats,
        metavar="H[,H...]",
        help="m above the ground, increasing: one hinge per push height",
    )
    st.add_argument(
        "--push-heights-from",
        type=Path,
        metavar="DIR",
        help="read the push heights from DIR/pulls.yaml (each entry's 'distance' on one branch, "
        "m above the ground, as import-csv --grasp-distance wrote it) and rewrite DIR/pulls.yaml "
        "to point at the chain's links",
    )
    st.add_argument("--base-diameter", type=float, metavar="M", help="m, diameter at the ground")
    st.add_argument("--tip-diameter", type=float, metavar="M", help="m, diameter at the tip")
    st.add_argument(
        "--diameters",
        type=_floats,
        metavar="D[,D...]",
        help="m, the diameter at each push height (instead of, or with, base and tip)",
    )
    add_qsm_options(p)
    st.add_argument(
        "--tie-scale",
        type=_tie_scale,
        metavar="TAU|none",
        help="as infer --tie-scale: each hinge's log-stiffness deviates from the beam-matched "
        "shape by Normal(0, TAU) (default 0.1); 'none': a hard tie (one free scale)",
    )
    st.add_argument(
        "--prb-gamma",
        type=float,
        metavar="G",
        help="pseudo-rigid-body characteristic radius: each hinge sits (1 - G) of the way from "
        "the push height below to its own (default 0.85, Howell's)",
    )
    st.add_argument(
        "--direction",
        metavar="D",
        help="the data set's default push direction, as import-csv --direction: down | "
        "horizontal | X,Y,Z (default horizontal)",
    )
    add_deprecated(p, "--grasp", "--grasp-branch", "the name of the grasped branch everywhere")
    add_deprecated(
        p,
        "--iterations",
        "--lsystem-iterations",
        "in `tree` it was the L-system's rewriting passes; --iterations is the sampler's "
        "iterations in infer and calibrate",
    )
    return p


def _tie_scale(text: str):
    """argparse type of ``--tie-scale``: a positive number or ``none`` (a hard tie)."""
    if text.strip().lower() in (_NO_TIE_SCALE, "hard"):
        return _NO_TIE_SCALE
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not (np.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"expected a positive number or 'none', got {text!r}")
    return v
