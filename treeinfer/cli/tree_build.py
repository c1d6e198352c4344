"""``treeinfer tree``: building the tree from the parsed arguments (generate, convert, a
user's own model) and printing it; the parser is in :mod:`treeinfer.cli.tree` (split from it
as a pure move, to keep modules under 500 lines)."""

from __future__ import annotations

import argparse
import json
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .. import __version__
from ..errors import ConfigError
from ..io.atomic import atomic_write_text
from ..io.ownership import claim_output_files, retire_output_files
from ..tree import generators as gen
from ..tree.description import Bounds, load_tree, tree_from_dict, tree_to_dict, world_frames
from ..tree.export import to_mjcf
from ..tree.urdf import to_urdf
from .common import (
    EXIT_OK,
    TREE_SUFFIXES,
    print_model_report,
)

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
    "tree_name": ("name", frozenset({"chain", "fractal", "lsystem", "explicit", "stem"})),
    "base_position": (
        "base_position",
        frozenset({"chain", "fractal", "lsystem", "explicit", "stem"}),
    ),
    "base_pitch": ("base_pitch_deg", frozenset({"chain", "fractal", "lsystem", "explicit"})),
    "base_yaw": ("base_yaw_deg", frozenset({"chain", "fractal", "lsystem", "explicit", "stem"})),
    "stem_height": ("height", frozenset({"stem"})),
    "push_heights": ("push_heights", frozenset({"stem"})),
    "base_diameter": ("base_diameter", frozenset({"stem"})),
    "tip_diameter": ("tip_diameter", frozenset({"stem"})),
    "diameters": ("diameters", frozenset({"stem"})),
    "tie_scale": ("tie_scale", frozenset({"stem"})),
    "prb_gamma": ("gamma", frozenset({"stem"})),
    "direction": ("direction", frozenset({"stem"})),
}

_NO_TIE_SCALE = "none"


def _parse_rules(items: Sequence[str]) -> dict[str, Any]:
    """``['F=FF', 'X=0.5:F[+X]', 'X=0.5:F[-X]']`` -> the rules mapping of ``generators.lsystem``."""
    grouped: dict[str, list[tuple[float | None, str]]] = {}
    for item in items:
        sym, eq, succ = item.partition("=")
        sym = sym.strip()
        if not eq or len(sym) != 1:
            raise ConfigError(
                f"--rule {item!r}: expected SYMBOL=SUCCESSOR with a one-character symbol, e.g. "
                "'F=FF-[-F+F]'"
            )
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
                f"--rule: symbol '{sym}' has {len(alts)} rules; give each a probability, e.g. "
                f"'{sym}=0.5:...'"
            )
        else:
            rules[sym] = [(pr, s) for pr, s in alts]
    return rules


def _tree_settings(args: argparse.Namespace, kind: str) -> dict[str, Any]:
    """Generator keyword arguments from the options the user gave; refuse ones ``kind`` ignores."""
    out: dict[str, Any] = {}
    for dest, (arg, kinds) in _GENERATOR_OPTIONS.items():
        value = getattr(args, dest)
        if value is None:
            continue
        if kind not in kinds:
            flag = "--" + dest.replace("_", "-") if dest != "tree_name" else "--name"
            raise ConfigError(
                f"{flag} does not apply to --kind {kind} (it is for: {', '.join(sorted(kinds))})"
            )
        if dest == "rule":
            value = _parse_rules(value)
        elif dest == "tie_scale" and value == _NO_TIE_SCALE:
            value = None
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
    from ..tree.description import read_tree_file

    d = read_tree_file(path)
    return d if isinstance(d, dict) else {}


def _convert(tree, settings: dict[str, Any], source: Path):
    """Apply grasp/inference/base options to a loaded tree, through its file representation
    so that every value is validated exactly like a tree file."""

    d = tree_to_dict(tree)
    if "name" in settings:
        d["name"] = settings["name"]
    if "grasp" in settings:
        d["grasp"]["branch"] = settings["grasp"]
    if "grasp_fraction" in settings:
        d["grasp"]["fraction"] = settings["grasp_fraction"]
    for key, fld in (
        ("base_position", "position"),
        ("base_pitch_deg", "pitch_deg"),
        ("base_yaw_deg", "yaw_deg"),
    ):
        if key in settings:
            d["base"][fld] = list(settings[key]) if key == "base_position" else settings[key]
    first = tree.bounds[tree.inferred[0]]
    if {"grasp", "levels", "bounds"} & set(settings):
        # the inferred joints (or their box) change: one box for all, from --k?-bounds or the first
        # joint
        bd = settings.get("bounds", first)
        d["inference"] = {
            "levels": settings.get("levels", tree.n_inferred),
            "prior": {"kp": list(bd.kp), "kd": list(bd.kd)},
        }
    return tree_from_dict(d, source=str(source))


def _summary(tree, path: Path) -> str:
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
        f"({tree.grasp_fraction * g.length:.3g} m from its joint; rest position "
        f"{np.round(c, 3).tolist()} m)"
    )
    lines.append(f"  inferred joints ({tree.n_inferred}): {', '.join(tree.inferred)}")
    lines.append(f"  parameters: {', '.join(tree.parameter_labels())}")
    boxes = {(tree.bounds[n].kp, tree.bounds[n].kd) for n in tree.inferred}
    if len(boxes) == 1:
        ((kp, kd),) = boxes
        lines.append(
            f"  prior box: Kp in [{kp[0]:g}, {kp[1]:g}] N m/rad, Kd in [{kd[0]:g}, {kd[1]:g}] N "
            "m s/rad"
        )
    else:
        lines.append("  prior box: per joint (see the file)")
    return "\n".join(lines)


def run_tree(args: argparse.Namespace) -> int:
    out: Path = args.out
    inputs = [args.source, args.model, getattr(args, "push_heights_from", None)]
    claim_output_files([out, args.mjcf, args.urdf], args.force, inputs)  # before any work
    if out.suffix.lower() not in TREE_SUFFIXES:
        raise ConfigError(f"--out {out}: a tree file must end in {', '.join(TREE_SUFFIXES)}")
    if args.model is not None or args.repair_inertia is not None:
        return _run_tree_model(args)
    kind = args.kind or ("explicit" if args.source is not None else "fractal")
    settings = _tree_settings(args, kind)
    pulls_dir = getattr(args, "push_heights_from", None)
    if pulls_dir is not None:
        if kind != "stem":
            raise ConfigError(
                f"--push-heights-from does not apply to --kind {kind} (it is for: stem)"
            )
        if "push_heights" in settings:
            raise ConfigError("give --push-heights or --push-heights-from, not both")
        settings["push_heights"] = [h for h, _ in _pull_heights(pulls_dir).values()]
        settings["push_heights"] = sorted(set(settings["push_heights"]))
    if kind == "stem" and args.source is None:
        need = {
            "height": "--stem-height",
            "push_heights": "--push-heights (or --push-heights-from)",
        }
        missing = [flag for key, flag in need.items() if key not in settings]
        if missing:
            raise ConfigError(f"--kind stem needs {' and '.join(missing)}")

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
    retire_output_files(targets, args.force, inputs)  # --force keeps what it replaces

    if generator_cfg is not None and kind != "explicit":
        gen.dump_generated(
            generator_cfg,
            out,
            comment=f"Written by treeinfer {__version__}: treeinfer tree --kind {kind}",
        )
    else:
        d = tree_to_dict(tree)
        if generator_cfg is not None:
            d["generator"] = generator_cfg
        text = (
            json.dumps(d, indent=2) + "\n"
            if out.suffix.lower() == ".json"
            else yaml.safe_dump(d, sort_keys=False)
        )
        atomic_write_text(out, text)
    print(_summary(tree, out))
    if kind == "stem":
        _report_stem(tree, generator_cfg, pulls_dir)
    if mjcf is not None:
        atomic_write_text(args.mjcf, mjcf)
        print(f"wrote {args.mjcf} (MJCF)")
    if urdf is not None:
        atomic_write_text(args.urdf, urdf)
        print(f"wrote {args.urdf} (URDF)")
    return EXIT_OK


def _pull_heights(folder: Path) -> dict[str, tuple[float, Any]]:
    """``{csv name: (height m, direction)}`` from ``folder/pulls.yaml`` written with
    ``import-csv --grasp-branch NAME --grasp-distance H`` (H above the ground, one branch
    name for every entry).

    Raises:
        ConfigError: no pulls file, an entry without a distance, several branch names, or
            entries that already name a generated chain's links.
    """
    from ..data.pulls import PULLS_FILE, read_pulls

    path = Path(folder) / PULLS_FILE
    if not path.is_file():
        raise ConfigError(
            f"--push-heights-from {folder}: no {PULLS_FILE} there (import-csv writes it)"
        )
    pf = read_pulls(path)
    if not pf.pulls:
        raise ConfigError(f"{path}: no entries under 'pulls'")
    out, branches = {}, set()
    for name, spec in pf.pulls.items():
        own = spec.fraction is not None or spec.distance is not None
        dist = spec.distance if own else pf.default.distance
        branch = spec.branch if spec.branch is not None else pf.default.branch
        if dist is None:
            raise ConfigError(
                f"{path}: pulls.{name}: no 'distance' (the push height above the ground); "
                "import with --grasp-distance H, or give --push-heights"
            )
        branches.add(branch)
        direction = spec.direction if spec.direction is not None else pf.default.direction
        out[name] = (round(float(dist), 9), direction)
    chain = sorted(str(b) for b in branches if re.fullmatch(r"stub|link\d+", str(b)))
    if chain:
        raise ConfigError(
            f"{path}: entries already name a generated chain's link ('{chain[0]}'); their "
            "distances are from that link's joint, not the ground: give --push-heights"
        )
    if len(branches) > 1:
        raise ConfigError(
            f"{path}: entries name several branches {sorted(map(str, branches))}; the push heights "
            "are read as distances from the ground along one stem (give --push-heights instead)"
        )
    return out


def _report_stem(tree, cfg, pulls_dir) -> None:
    """Print where each push height lies on the chain (import-csv's grasp options); with
    ``pulls_dir``, rewrite its pulls.yaml to point at those links (the original kept)."""
    import shutil

    from ..data.pulls import PULLS_FILE, PullSpec, read_pulls, write_pulls

    points = gen.stem_push_points(tree, cfg["push_heights"])
    if tree.tie_shape is not None:
        shape = ", ".join(f"{n} {v:.3g}" for n, v in zip(tree.inferred, tree.tie_shape))
        tau = "hard" if tree.tie_scale is None else f"soft, tie_scale {tree.tie_scale:g}"
        print(f"  tie: shape ({tau}): {shape}")
    print("  push heights (import-csv grasp options):")
    for h, branch, dist in points:
        print(f"    {h:g} m: --grasp-branch {branch} --grasp-distance {dist:.6g}")
    if pulls_dir is None:
        return
    path = Path(pulls_dir) / PULLS_FILE
    heights = _pull_heights(pulls_dir)
    at = {round(h, 9): (b, d) for h, b, d in points}
    pf = read_pulls(path)
    new = {
        name: PullSpec(branch=at[h][0], distance=at[h][1], direction=direction)
        for name, (h, direction) in heights.items()
    }
    backup = path.with_name(PULLS_FILE + ".orig")
    if not backup.exists():
        shutil.copyfile(path, backup)
    write_pulls(
        path,
        new,
        default=PullSpec(direction=pf.default.direction),
        header=f"rewritten by treeinfer tree --kind stem for {tree.name}: heights above the "
        f"ground are now (link, distance from its joint); the original is {backup.name}",
    )
    print(f"  rewrote {path} to the chain's links (original: {backup})")


def _run_tree_model(args: argparse.Namespace) -> int:
    """``tree --model FILE``: describe a user's URDF/MJCF (or attach it to ``--from``'s tree),
    check that it prepares for the simulator, and write the tree file."""
    from ..tree.usermodel import attach_model, prepare_user_model, tree_from_model

    out: Path = args.out
    if args.kind not in (None, "explicit"):
        raise ConfigError(f"--model describes the model file; --kind {args.kind} does not apply")
    if args.mjcf is not None or args.urdf is not None:
        raise ConfigError(
            "--mjcf/--urdf export the tree's own cylinders; with --model the model file itself "
            "is simulated"
        )
    settings = _tree_settings(args, "explicit")
    if args.source is not None:
        tree = load_tree(args.source)
        tree = _convert(tree, settings, args.source) if settings else tree
        tree = attach_model(tree, args.model, args.repair_inertia)
    else:
        if args.model is None:
            raise ConfigError("--repair-inertia needs the model: give --model FILE")
        kw = {k: v for k, v in settings.items() if k != "grasp_fraction"}
        for key in ("base_position", "base_pitch_deg", "base_yaw_deg"):
            kw.pop(key, None)
        tree = tree_from_model(
            args.model,
            grasp_fraction=settings.get("grasp_fraction", 1.0),
            repair_inertia=args.repair_inertia,
            **kw,
        )
    retire_output_files([out], args.force, [args.source, args.model])
    prepared = prepare_user_model(tree)  # every check now, not at the first simulation
    d = tree_to_dict(tree)
    text = (
        json.dumps(d, indent=2) + "\n"
        if out.suffix.lower() == ".json"
        else yaml.safe_dump(d, sort_keys=False)
    )
    atomic_write_text(out, text)
    print(_summary(tree, out))
    print_model_report(prepared.report)
    return EXIT_OK
