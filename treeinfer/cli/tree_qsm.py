"""``treeinfer tree --from-qsm FILE``: a tree from a QSM cylinder table (TreeQSM, SimpleForest,
aRchi), with the figure of the conversion written beside it. The conversion itself is
:func:`treeinfer.tree.qsm_convert.tree_from_qsm`."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import ConfigError
from ..io.atomic import atomic_write_text
from ..io.ownership import claim_output_files, retire_output_files
from .common import EXIT_OK, TREE_SUFFIXES, _triple

QSM_EPILOG = """\
QSMs (--from-qsm FILE): TreeQSM (.mat, cylinder_*.txt, cyl_data_*.txt), SimpleForest CSV or aRchi
CSV, in metres unless --qsm-units says otherwise. The chain from the grasp point (--grasp-point
in the file's coordinates, or --grasp-cylinder; default: the stem's top) down to the base
becomes the tree's links, the rest of the tree is welded into their bodies (--rest),
and the joints' prior boxes come from the wood (--species, --wood-modulus, --wood-density).
  treeinfer tree --from-qsm tree.mat --grasp-point=1.69,-16.09,256.03 --joint-spacing 0.5 \\
      --out tree.yaml      # also writes tree_qsm.png (the cylinders, links and joints)
"""


def add_qsm_options(p: argparse.ArgumentParser) -> None:
    from ..tree.qsm import FORMATS, UNITS
    from ..tree.qsm_convert import RESTS
    from ..tree.qsm_wood import SPECIES

    q = p.add_argument_group("QSM (a tree from a point-cloud reconstruction: --from-qsm FILE)")
    q.add_argument(
        "--from-qsm",
        type=Path,
        metavar="FILE",
        help="QSM cylinder table to convert: TreeQSM .mat or text, SimpleForest or aRchi CSV",
    )
    q.add_argument(
        "--qsm-format", choices=FORMATS, help="the QSM's layout (default: detected from the file)"
    )
    q.add_argument(
        "--qsm-units", choices=tuple(UNITS), help="the QSM's length unit (default: m, checked)"
    )
    q.add_argument(
        "--grasp-point",
        type=_triple,
        metavar="X,Y,Z",
        help="grasp point in the QSM's own coordinates and unit; the nearest cylinder is grasped "
        "(write --grasp-point=X,Y,Z when X is negative)",
    )
    q.add_argument(
        "--grasp-cylinder", type=int, metavar="ID", help="grasped cylinder, by the file's id"
    )
    q.add_argument(
        "--prune-diameter",
        type=float,
        metavar="M",
        help="m: cylinders thinner than this, and all they carry, are no links (default 0)",
    )
    q.add_argument(
        "--max-order", type=int, metavar="N", help="axes of a higher order are no links (0: stem)"
    )
    q.add_argument(
        "--joint-spacing",
        type=float,
        metavar="M",
        help="m: also a joint about every M metres along an axis (default: joints only at the "
        "base and where the chain changes axis)",
    )
    q.add_argument(
        "--max-deviation",
        type=float,
        metavar="M",
        help="m: also a joint where an axis bends, so that every link follows its QSM axis "
        "within M metres (default: no such joints)",
    )
    q.add_argument(
        "--rest",
        choices=RESTS,
        help="the tree off the grasp's chain: lump (default: its mass welded onto the chain), "
        "drop, or keep (every unpruned axis as jointed links with fixed gains)",
    )
    q.add_argument(
        "--species",
        help=f"wood for masses and prior boxes (default green-hardwood): {', '.join(SPECIES)}",
    )
    q.add_argument("--wood-density", type=float, metavar="KG_M3", help="green wood density")
    q.add_argument("--wood-modulus", type=float, metavar="GPA", help="modulus of elasticity, GPa")
    q.add_argument(
        "--plot", type=Path, metavar="FILE", help="the figure (default: OUT's name + _qsm.png)"
    )


# options of `tree` that mean something with --from-qsm (the others are refused)
_APPLY = {"tree_name", "levels", "kp_bounds", "kd_bounds"}


def run_tree_qsm(args: argparse.Namespace) -> int:
    from ..tree.description import Bounds, tree_to_dict
    from ..tree.export import to_mjcf
    from ..tree.qsm_convert import tree_from_qsm
    from ..tree.urdf import to_urdf
    from .tree_build import _GENERATOR_OPTIONS, _summary

    out: Path = args.out
    plot = args.plot if args.plot is not None else out.with_name(out.stem + "_qsm.png")
    inputs = [args.from_qsm]
    claim_output_files([out, plot, args.mjcf, args.urdf], args.force, inputs)
    if out.suffix.lower() not in TREE_SUFFIXES:
        raise ConfigError(f"--out {out}: a tree file must end in {', '.join(TREE_SUFFIXES)}")
    if args.source is not None or args.model is not None or args.kind is not None:
        raise ConfigError("--from-qsm builds the tree itself: leave out --from, --model, --kind")
    for dest in _GENERATOR_OPTIONS:
        if dest not in _APPLY and getattr(args, dest, None) is not None:
            flag = "--" + dest.replace("_", "-")
            hint = " (give --grasp-point X,Y,Z or --grasp-cylinder ID)" if dest == "grasp" else ""
            raise ConfigError(f"{flag} does not apply to --from-qsm{hint}")
    bounds = None
    if args.kp_bounds is not None or args.kd_bounds is not None:
        if args.kp_bounds is None or args.kd_bounds is None:
            raise ConfigError("with --from-qsm give both --kp-bounds and --kd-bounds, or neither")
        bounds = Bounds(kp=tuple(args.kp_bounds), kd=tuple(args.kd_bounds))
    result = tree_from_qsm(
        args.from_qsm,
        grasp_point=args.grasp_point,
        grasp_cylinder=args.grasp_cylinder,
        prune_diameter=0.0 if args.prune_diameter is None else args.prune_diameter,
        max_order=args.max_order,
        joint_spacing=args.joint_spacing,
        max_deviation=args.max_deviation,
        rest=args.rest or "lump",
        levels=args.levels,
        species=args.species,
        density=args.wood_density,
        modulus=None if args.wood_modulus is None else args.wood_modulus * 1e9,
        bounds=bounds,
        name=args.tree_name,
        fmt=args.qsm_format,
        units=args.qsm_units,
    )
    tree = result.tree
    mjcf = to_mjcf(tree) if args.mjcf is not None else None
    urdf = to_urdf(tree) if args.urdf is not None else None
    text = _tree_text(tree_to_dict(tree), out, result)
    targets = [p for p in (out, plot, args.mjcf, args.urdf) if p is not None]
    retire_output_files(targets, args.force, inputs)
    atomic_write_text(out, text)
    _write_plot(result, plot)
    print(_summary(tree, out))
    print(_qsm_lines(result, plot))
    if mjcf is not None:
        atomic_write_text(args.mjcf, mjcf)
        print(f"wrote {args.mjcf} (MJCF)")
    if urdf is not None:
        atomic_write_text(args.urdf, urdf)
        print(f"wrote {args.urdf} (URDF)")
    return EXIT_OK


def _tree_text(d: dict, out: Path, result) -> str:
    import json

    import yaml

    from .. import __version__

    if out.suffix.lower() == ".json":
        return json.dumps(d, indent=2) + "\n"
    r = result.report
    head = (
        f"# Written by treeinfer {__version__}: treeinfer tree --from-qsm {r['source']}\n"
        f"# {r['format']}, {r['cylinders']} cylinders; grasped cylinder {r['grasp_cylinder_id']};"
        f" wood: {r['wood']}\n"
    )
    return head + yaml.safe_dump(d, sort_keys=False)


def _write_plot(result, path: Path) -> None:
    import io

    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from ..io.atomic import atomic_write_bytes
    from ..tree.qsm_plot import plot_qsm

    fig, _ = plot_qsm(result)
    buf = io.BytesIO()
    fig.savefig(buf, format=path.suffix.lstrip(".") or "png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def _qsm_lines(result, plot: Path) -> str:
    r = result.report
    return "\n".join(
        [
            f"  QSM: {r['source']} ({r['format']}, {r['units']}): {r['cylinders']} cylinders, "
            f"{r['qsm_length_m']:.3g} m of cylinders, {r['qsm_height_m']:.3g} m tall, "
            f"{r['mass_kg']:.3g} kg of wood",
            f"  links: {r['links']} ({r['link_length_m']:.3g} m, {r['link_mass_kg']:.3g} kg); "
            f"lumped {r['lumped_mass_kg']:.3g} kg into {r['lumps']} links' bodies, dropped "
            f"{r['dropped_mass_kg']:.3g} kg; {r['pruned']} cylinders pruned",
            f"  grasp: cylinder {r['grasp_cylinder_id']} ({r['grasp_offset_m']:.3g} m from the "
            f"point); links end within {r['max_end_error_m']:.3g} m of the QSM's",
            f"  wood: {r['wood']}",
            f"wrote {plot} (the QSM with the links and joints)",
        ]
    )
