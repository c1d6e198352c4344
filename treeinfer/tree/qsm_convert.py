"""A QSM's cylinders as a treeinfer :class:`~treeinfer.tree.types.Tree`.

Steps (:func:`tree_from_qsm`):

1. **Axes.** The base is moved to the origin. At every fork the child carrying the most
   cylinder length (its *growth length*) continues the parent's axis; the others start new
   axes (the stem is axis 0). The same rule for every tool, so that the three reconstructions
   of one tree give the same kind of axes whatever their own branch ids.
2. **What becomes links.** The *path* runs from the grasped cylinder (nearest to a 3-D grasp
   point, a cylinder id, or by default the stem's top) down to the base. ``rest="lump"``
   (default) or ``"drop"``: only the path, and the grasped axis beyond the grasp point, become
   links; ``"keep"``: every cylinder not pruned does. Pruning removes cylinders thinner than
   ``prune_diameter`` or of a higher axis order than ``max_order``, with all they carry; the
   path is never pruned.
3. **Links and joints.** Consecutive cylinders of an axis merge into one straight link from
   its joint to the last cylinder's end. Joints sit at the base, where an axis leaves its
   parent, at forks of kept axes (``keep``; not closer than ``min_link_length``), where the
   axis bends (``max_deviation``: every cylinder end within that many m of its link's line)
   and every ``joint_spacing`` m along an axis (split into equal parts at cylinder ends).
   A link's radius keeps its cylinders' wood volume; its base radius (taper) sets the
   stiffness box.
4. **Hinge axes.** A joint is one hinge across its link. On the grasp's path it lies along the
   moment of the pull (``pull_direction``, default down) about the joint; off the path, across
   the link's bend under gravity. Where the link's direction lies within
   ``hinge_tolerance_deg`` of the plane that gives that hinge without a twist (the normal of
   the plane of the two links), that plane is used and the link is turned by at most that
   angle (and so that its end moves by at most ``SNAP_DISTANCE``); each link aims at its own
   QSM end, so the error does not add up along the tree. Elsewhere the link keeps its exact
   direction and its frame is twisted about its own axis (``twist_deg``) to give the hinge.
5. **The rest.** ``lump``: every cylinder not in a link is welded into the body of the link it
   hangs from as that link's ``lump`` (:mod:`treeinfer.tree.lump`): their mass, centre of mass
   and inertia (each cylinder's own plus the parallel-axis terms) are kept exactly, and the
   model has one body per joint, like a hand-written tree; ``drop``: left out.
6. **Priors** from the wood (:mod:`treeinfer.tree.qsm_wood`): the inferred joints (the path's,
   all by default, else the first ``levels`` up from the grasp) get a stiffness box from the
   link's base radius and length and a damping box from the inertia the joint carries; the
   other joints get the boxes' geometric means as fixed gains.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError, TreeFileError
from .description import make_tree
from .lump import cylinders_lump
from .qsm import Cylinders, children_of, read_qsm, topological_order
from .qsm_geometry import (
    base_rot,
    carried_inertia,
    child_angles,
    clip_box,
    hinge_wanted,
    link_names,
    nearest_cylinder,
    on_segment,
    root_angles,
    round_sig,
    split_bends,
    split_even,
    unit_vector,
)
from .qsm_wood import Wood, damping_box, stiffness_box, wood
from .types import KD_RANGE, KP_RANGE, Bounds, Branch, Tree, local_rotation

RESTS = ("lump", "drop", "keep")
SNAP_DISTANCE = 0.02  # m: how far a link's end may move when it is turned to a wanted hinge
_MIN_LUMP_MASS = 1e-6  # kg; lighter remainders are left out (reported as dropped)


@dataclass(frozen=True)
class QsmLink:
    """One link of the converted tree: its cylinders (indices into the table), its joint and
    end in the tree's frame (base at the origin, m), base and tip radius (m)."""

    name: str
    cylinders: tuple[int, ...]
    joint: np.ndarray
    end: np.ndarray
    base_radius: float
    tip_radius: float
    inferred: bool = False


@dataclass(frozen=True)
class QsmTree:
    """What :func:`tree_from_qsm` returns: the ``tree``, the ``cylinders`` read (file frame),
    the ``origin`` subtracted (m), the ``links`` (those carrying a welded lump in ``lumps``), which
    cylinders became links (``in_links``) or were lumped (``lumped``), the grasped cylinder's
    index, and a ``report`` of figures (lengths, masses, counts)."""

    tree: Tree
    cylinders: Cylinders
    origin: np.ndarray
    links: tuple[QsmLink, ...]
    lumps: tuple[str, ...]
    in_links: np.ndarray
    lumped: np.ndarray
    grasp_cylinder: int
    grasp_point: np.ndarray
    wood: Wood
    report: dict[str, Any] = field(default_factory=dict)


def tree_from_qsm(
    source: str | Path | Cylinders,
    *,
    grasp_point: tuple[float, float, float] | None = None,
    grasp_cylinder: int | None = None,
    prune_diameter: float = 0.0,
    max_order: int | None = None,
    joint_spacing: float | None = None,
    max_deviation: float | None = None,
    rest: str = "lump",
    levels: int | None = None,
    species: str | None = None,
    density: float | None = None,
    modulus: float | None = None,
    bounds: Bounds | None = None,
    name: str | None = None,
    fmt: str | None = None,
    units: str | None = None,
    pull_direction: tuple[float, float, float] = (0.0, 0.0, -1.0),
    hinge_tolerance_deg: float = 5.0,
    min_link_length: float = 0.05,
) -> QsmTree:
    """Convert a QSM (a file, read with :func:`treeinfer.tree.qsm.read_qsm`, or a table) into a
    tree (module docstring). ``grasp_point`` is in the file's coordinates and unit;
    ``grasp_cylinder`` is a cylinder id as the file numbers them; lengths in m. ``bounds``
    replaces the wood's prior box for every inferred joint.

    Raises:
        TreeFileError: a bad QSM; ConfigError: bad options.
    """
    cyl = source if isinstance(source, Cylinders) else read_qsm(source, fmt, units)
    _check_options(grasp_point, grasp_cylinder, prune_diameter, joint_spacing, rest, levels)
    if max_deviation is not None and not (math.isfinite(max_deviation) and max_deviation > 0):
        raise ConfigError(f"max deviation {max_deviation!r}: expected a positive number (m)")
    if max_order is not None and (isinstance(max_order, bool) or max_order < 0):
        raise ConfigError(f"max order {max_order!r}: expected an integer >= 0 (0: the stem)")
    w = wood(species, density, modulus)
    root = int(np.flatnonzero(cyl.parent < 0)[0])
    origin = cyl.start[root].copy()
    start, end = cyl.start - origin, cyl.end - origin
    length, radius = cyl.length, cyl.radius
    topo = topological_order(cyl)
    children = children_of(cyl)

    # 1. axes by growth length
    growth = length.copy()
    for i in reversed(topo):
        if cyl.parent[i] >= 0:
            growth[cyl.parent[i]] += growth[i]
    cont = np.full(cyl.n, -1)
    for i in range(cyl.n):
        if children[i]:
            cont[i] = max(children[i], key=lambda c: (growth[c], radius[c]))
    axis = np.full(cyl.n, -1)
    axes: list[list[int]] = []
    axis_order: list[int] = []
    for i in topo:
        p = int(cyl.parent[i])
        if p >= 0 and cont[p] == i:
            axis[i] = axis[p]
        else:
            axis[i] = len(axes)
            axes.append([])
            axis_order.append(0 if p < 0 else axis_order[axis[p]] + 1)
        axes[axis[i]].append(i)

    # 2. the grasp, pruning, what becomes links
    scale = {"m": 1.0, "cm": 0.01, "mm": 0.001}[cyl.units]
    if grasp_cylinder is not None:
        g = cyl.index_of(grasp_cylinder)
        gp = end[g]
    elif grasp_point is not None:
        gp = np.asarray(grasp_point, float) * scale - origin
        g = nearest_cylinder(gp, start, end, radius)
    else:
        g = axes[0][-1]  # the stem's top
        gp = end[g]
    path = set()
    i = g
    while i >= 0:
        path.add(i)
        i = int(cyl.parent[i])
    pruned = np.zeros(cyl.n, bool)
    for i in topo:
        p = int(cyl.parent[i])
        cut = 2 * radius[i] < prune_diameter or (
            max_order is not None and axis_order[axis[i]] > max_order
        )
        pruned[i] = i not in path and (cut or (p >= 0 and pruned[p]))
    if rest == "keep":
        in_links = ~pruned
    else:
        in_links = np.zeros(cyl.n, bool)
        in_links[list(path)] = True
        for i in axes[axis[g]][axes[axis[g]].index(g) + 1 :]:
            if pruned[i]:
                break
            in_links[i] = True

    # 3. links: runs of an axis between cuts
    runs: list[tuple[list[int], int]] = []  # (cylinders, axis)
    for a, cyls in enumerate(axes):
        kept = [c for c in cyls if in_links[c]]
        if not kept:
            continue
        cuts = [0]
        if rest == "keep":
            run_len = 0.0
            total = float(sum(length[c] for c in kept))
            done = 0.0
            for k, c in enumerate(kept[:-1]):
                run_len += length[c]
                done += length[c]
                forks = any(in_links[ch] and ch != cont[c] for ch in children[c])
                if forks and run_len >= min_link_length and total - done >= min_link_length:
                    cuts.append(k + 1)
                    run_len = 0.0
        pieces = []
        for s, e in zip(cuts, cuts[1:] + [len(kept)]):
            for part in split_bends(kept[s:e], start, end, max_deviation):
                pieces += split_even(part, length, joint_spacing)
        runs += [(piece, a) for piece in pieces]

    axis_names, run_names = link_names(runs)
    link_of = np.full(cyl.n, -1)
    for k, (piece, _) in enumerate(runs):
        link_of[piece] = k

    # 4. geometry, parents first (runs are in axis creation order, which is topological)
    pull = unit_vector(np.asarray(pull_direction, float))
    tol = math.radians(hinge_tolerance_deg)
    on_path = {int(link_of[c]) for c in path}

    def snap_angle(v) -> float:
        # turn a link only so far that its end moves by at most SNAP_DISTANCE
        return min(tol, math.asin(min(1.0, SNAP_DISTANCE / max(float(np.linalg.norm(v)), 1e-9))))

    frames: list[tuple[np.ndarray, np.ndarray, float]] = []
    branches: list[Branch] = []
    base_pitch = base_yaw = 0.0
    for k, (piece, a) in enumerate(runs):
        c0, c1 = piece[0], piece[-1]
        vol = float(np.sum(math.pi * radius[piece] ** 2 * length[piece]))
        if k == 0:
            p0 = start[c0]
            d = unit_vector(end[c1] - p0)
            want = hinge_wanted(gp - p0, pull, d, None)
            base_pitch, base_yaw = root_angles(d, want, snap_angle(end[c1] - p0))
            rot = base_rot(base_pitch, base_yaw)
            attach, pname, ang, azi, twist = 1.0, None, 0.0, 0.0, 0.0
            wp = want - np.dot(want, d) * d
            if abs(float(rot[:, 1] @ wp)) < math.cos(tol) * np.linalg.norm(wp):
                # a leaning stem whose heading gives another hinge: twisted about its axis
                twist = math.atan2(float(wp @ rot[:, 2]), float(wp @ rot[:, 1]))
                rot = rot @ local_rotation(Branch("x", None, 1.0, 1.0, twist_deg=_deg(twist)))
        else:
            first_of_axis = axes[a][0] == c0
            pk = int(link_of[cyl.parent[c0]]) if first_of_axis else k - 1
            pp, pr, pl = frames[pk]
            if first_of_axis:
                t = float(np.dot(start[c0] - pp, pr[:, 0])) / pl
                attach = float(np.clip(t, 1e-3, 1.0))
            else:
                attach = 1.0
            p0 = pp + attach * pl * pr[:, 0]
            d = unit_vector(end[c1] - p0)
            r_grasp = gp - p0 if k in on_path else None
            want = hinge_wanted(r_grasp, pull, d, frames[0][1][:, 1])
            ang, azi, turn = child_angles(d, pr, want, tol, snap_angle(end[c1] - p0))
            twist = 0.0
            if turn is not None:  # the exact direction, the frame twisted to the hinge
                ang, azi, twist = turn[0], turn[1], azi
            pname = run_names[pk]
            rot = pr @ local_rotation(
                Branch("x", None, 1.0, 1.0, _deg(ang), _deg(azi), twist_deg=_deg(twist))
            )
        ln = float(np.linalg.norm(end[c1] - p0))
        if ln <= 0:
            raise TreeFileError(f"{cyl.where(c1)}: a link of zero length ends here")
        frames.append((p0, rot, ln))
        branches.append(
            Branch(
                name=run_names[k],
                parent=pname,
                length=round(ln, 6),
                radius=round(math.sqrt(vol / (math.pi * ln)), 6),
                angle_deg=_deg(ang),
                azimuth_deg=_deg(azi),
                attach=round(attach, 6),
                twist_deg=_deg(twist),
            )
        )
    link_index = {n: k for k, n in enumerate(run_names)}

    # 5. the rest: welded into the body of the link it hangs from, or dropped
    lumped = np.zeros(cyl.n, bool)
    lumps: list[str] = []
    mass = w.density * math.pi * radius**2 * length
    lumped_mass = dropped_mass = 0.0
    if rest != "drop":
        host = np.full(cyl.n, -1)
        for i in topo:  # parents first: a cylinder's host is its parent's
            p = int(cyl.parent[i])
            if not in_links[i]:
                host[i] = link_of[p] if in_links[p] else host[p]
        for h in range(len(runs)):
            sel = np.flatnonzero(host == h)
            if not len(sel) or mass[sel].sum() < _MIN_LUMP_MASS:
                continue
            lump = cylinders_lump(
                mass[sel], start[sel], end[sel], radius[sel], frames[h][0], frames[h][1]
            )
            bi = next(i for i, b in enumerate(branches) if b.name == run_names[h])
            branches[bi] = replace(branches[bi], lump=lump)
            lumps.append(run_names[h])
            lumped[sel] = True
            lumped_mass += lump.mass
    dropped_mass += float(mass[~in_links & ~lumped].sum())

    # 6. which joints are inferred, and the priors
    path_links = []
    k = int(link_of[g])
    by = {b.name: b for b in branches}
    name_k = run_names[k]
    while name_k is not None:
        if name_k in link_index:  # connectors (welded) have no joint
            path_links.append(name_k)
        name_k = by[name_k].parent
    inferred = path_links if levels is None else path_links[:levels]
    boxes = {}
    for k, (piece, _) in enumerate(runs):
        boxes[run_names[k]] = stiffness_box(w, float(radius[piece[0]]), frames[k][2])
    draft = _assemble(
        branches, run_names[int(link_of[g])], inferred, w, base_pitch, base_yaw, name, cyl
    )
    carried = carried_inertia(draft)
    bounds_map, fixed = {}, {}
    for n, kb in boxes.items():
        kp = clip_box(kb, KP_RANGE)
        kd = clip_box(damping_box(kp, carried[n]), KD_RANGE)
        if n in inferred:
            bounds_map[n] = bounds if bounds is not None else Bounds(kp=kp, kd=kd)
        else:
            fixed[n] = (math.sqrt(kp[0] * kp[1]), math.sqrt(kd[0] * kd[1]))
    all_branches = [
        Branch(
            **{**b.__dict__, "kp": round_sig(fixed[b.name][0]), "kd": round_sig(fixed[b.name][1])}
        )
        if b.name in fixed
        else b
        for b in branches
    ]
    gl = frames[int(link_of[g])]
    fraction = float(
        np.clip(np.dot(on_segment(gp, start[g], end[g]) - gl[0], gl[1][:, 0]), 0, None)
    )
    fraction = float(np.clip(fraction / gl[2], 1e-3, 1.0))
    tree = _assemble(
        all_branches,
        run_names[int(link_of[g])],
        inferred,
        w,
        base_pitch,
        base_yaw,
        name,
        cyl,
        bounds_map,
        fraction,
    )
    links = tuple(
        QsmLink(
            name=run_names[k],
            cylinders=tuple(int(c) for c in piece),
            joint=frames[k][0],
            end=frames[k][0] + frames[k][1][:, 0] * frames[k][2],
            base_radius=float(radius[piece[0]]),
            tip_radius=float(radius[piece[-1]]),
            inferred=run_names[k] in inferred,
        )
        for k, (piece, _) in enumerate(runs)
    )
    report = {
        "source": cyl.source,
        "format": cyl.fmt,
        "units": cyl.units,
        "cylinders": cyl.n,
        "qsm_length_m": float(length.sum()),
        "qsm_height_m": float(max(start[:, 2].max(), end[:, 2].max())),
        "axes": len(axes),
        "pruned": int(pruned.sum()),
        "links": len(links),
        "joints": len(links),
        "inferred": len(inferred),
        "lumps": len(lumps),
        "link_length_m": float(sum(f[2] for f in frames)),
        "link_cylinder_length_m": float(length[in_links].sum()),
        "max_end_error_m": float(
            max(np.linalg.norm(lk.end - end[lk.cylinders[-1]]) for lk in links)
        ),
        "height_m": float(max(max(f[0][2], (f[0] + f[1][:, 0] * f[2])[2]) for f in frames)),
        "mass_kg": float(mass.sum()),
        "link_mass_kg": float(mass[in_links].sum()),
        "lumped_mass_kg": float(lumped_mass),
        "dropped_mass_kg": float(dropped_mass),
        "grasp_cylinder_id": int(cyl.ids[g]),
        "grasp_branch": tree.grasp_branch,
        "grasp_fraction": tree.grasp_fraction,
        "grasp_offset_m": float(np.linalg.norm(on_segment(gp, start[g], end[g]) - gp)),
        "wood": w.name,
        "axis_names": axis_names,
    }
    return QsmTree(
        tree=tree,
        cylinders=cyl,
        origin=origin,
        links=links,
        lumps=tuple(lumps),
        in_links=in_links,
        lumped=lumped,
        grasp_cylinder=int(g),
        grasp_point=gp,
        wood=w,
        report=report,
    )


# ---- pieces ---------------------------------------------------------------------------------
def _check_options(grasp_point, grasp_cylinder, prune_diameter, joint_spacing, rest, levels):
    if grasp_point is not None and grasp_cylinder is not None:
        raise ConfigError("give a grasp point or a grasp cylinder, not both")
    if grasp_point is not None and (
        len(grasp_point) != 3 or not all(math.isfinite(float(x)) for x in grasp_point)
    ):
        raise ConfigError(f"grasp point {grasp_point!r}: expected three finite numbers X,Y,Z")
    if not (math.isfinite(prune_diameter) and prune_diameter >= 0):
        raise ConfigError(f"prune diameter {prune_diameter!r}: expected a number >= 0 (m)")
    if joint_spacing is not None and not (math.isfinite(joint_spacing) and joint_spacing > 0):
        raise ConfigError(f"joint spacing {joint_spacing!r}: expected a positive number (m)")
    if rest not in RESTS:
        raise ConfigError(f"rest {rest!r}: expected one of {', '.join(RESTS)}")
    if levels is not None and (isinstance(levels, bool) or levels < 1):
        raise ConfigError(f"levels {levels!r}: expected a positive integer")


def _deg(angle: float) -> float:
    return round(math.degrees(angle), 6)


def _assemble(branches, grasp, inferred, w, pitch, yaw, name, cyl, bounds=None, fraction=1.0):
    return make_tree(
        branches,
        grasp_branch=grasp,
        grasp_fraction=fraction,
        inferred=inferred,
        bounds=bounds if bounds is not None else Bounds(),
        name=name or Path(cyl.source).stem,
        base_pitch_deg=round(math.degrees(pitch), 6),
        base_yaw_deg=round(math.degrees(yaw), 6),
        density=round(w.density, 3),
    )
