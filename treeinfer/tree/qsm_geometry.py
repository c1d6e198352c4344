"""Geometry of the QSM conversion (:mod:`treeinfer.tree.qsm_convert`): nearest cylinder,
even splits, link names, hinge axes and frames, and the inertia a joint carries. Split from
the converter to keep modules short."""

from __future__ import annotations

import math

import numpy as np

from .types import (
    Branch,
    Tree,
    base_rotation,
    branch_inertial,
    local_rotation,
    world_frames,
)


def nearest_cylinder(p, start, end, radius) -> int:
    """The cylinder whose surface is nearest to ``p`` (distance to its axis segment minus its
    radius, floored at 0; ties to the thinner one)."""
    ab = end - start
    t = np.clip(np.einsum("ij,ij->i", p - start, ab) / np.einsum("ij,ij->i", ab, ab), 0, 1)
    dist = np.linalg.norm(start + t[:, None] * ab - p, axis=1)
    surf = np.maximum(dist - radius, 0.0)
    return int(np.lexsort((radius, surf))[0])


def on_segment(p, a, b) -> np.ndarray:
    ab = b - a
    t = float(np.clip(np.dot(p - a, ab) / float(np.dot(ab, ab)), 0.0, 1.0))
    return a + t * ab


def split_bends(piece: list[int], start, end, tol: float | None) -> list[list[int]]:
    """``piece`` cut at cylinder ends until every cylinder end lies within ``tol`` m of its
    link's straight line (Ramer-Douglas-Peucker: cut at the farthest end, recurse): joints
    where the axis bends."""
    if tol is None or len(piece) < 2:
        return [piece]
    a, b = start[piece[0]], end[piece[-1]]
    ab = b - a
    inner = end[piece[:-1]]
    t = np.clip((inner - a) @ ab / max(float(ab @ ab), 1e-300), 0.0, 1.0)
    dist = np.linalg.norm(a + t[:, None] * ab - inner, axis=1)
    k = int(np.argmax(dist))
    if dist[k] <= tol:
        return [piece]
    return split_bends(piece[: k + 1], start, end, tol) + split_bends(
        piece[k + 1 :], start, end, tol
    )


def split_even(piece: list[int], length: np.ndarray, spacing: float | None) -> list[list[int]]:
    """``piece`` cut at cylinder ends into ``round(L / spacing)`` parts of about equal length."""
    total = float(length[piece].sum())
    k = 1 if spacing is None else max(1, round(total / spacing))
    if k == 1 or len(piece) == 1:
        return [piece]
    cum = np.cumsum(length[piece])
    cuts = sorted({int(np.argmin(np.abs(cum - total * j / k))) + 1 for j in range(1, k)})
    cuts = [c for c in cuts if 0 < c < len(piece)]
    return [piece[s:e] for s, e in zip([0] + cuts, cuts + [len(piece)])]


def link_names(runs) -> tuple[dict[int, str], list[str]]:
    axis_names: dict[int, str] = {}
    count: dict[int, int] = {}
    for _, a in runs:
        if a not in axis_names:
            axis_names[a] = "stem" if a == 0 else f"b{len(axis_names)}"
        count[a] = count.get(a, 0) + 1
    seen: dict[int, int] = {}
    names = []
    for _, a in runs:
        seen[a] = seen.get(a, 0) + 1
        names.append(axis_names[a] if count[a] == 1 else f"{axis_names[a]}_{seen[a]}")
    return axis_names, names


def unit_vector(v) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 0 else np.array([0.0, 0.0, 1.0])


def base_rot(pitch: float, yaw: float) -> np.ndarray:
    return base_rotation(
        Tree(
            "x",
            (),
            "x",
            1.0,
            (),
            base_pitch_deg=math.degrees(pitch),
            base_yaw_deg=math.degrees(yaw),
        )
    )


def hinge_wanted(r_grasp, pull, d, fallback) -> np.ndarray:
    """The hinge axis a joint should have: along the moment of the pull at the grasp point
    about the joint (``r_grasp`` x ``pull``; joints on the grasp's path), else the axis gravity
    bends the link about (vertical x ``d``), else ``fallback`` (the root's hinge)."""
    moment = None if r_grasp is None else np.cross(r_grasp, pull)
    for v in (moment, np.cross([0.0, 0.0, 1.0], d)):
        if v is not None:
            v = v - np.dot(v, d) * d
            if np.linalg.norm(v) > 1e-6:
                return v / np.linalg.norm(v)
    return fallback if fallback is not None else np.array([0.0, 1.0, 0.0])


def root_angles(d, want, snap) -> tuple[float, float]:
    """Pitch and yaw (rad) of the root link: its hinge (horizontal, normal to the heading)
    along the horizontal part of ``want`` when ``d`` lies within ``snap`` rad of that heading's
    vertical plane, else exactly along ``d``."""
    heading = np.array([want[1], -want[0], 0.0])
    if np.linalg.norm(heading) > 1e-6:
        heading /= np.linalg.norm(heading)
        side = np.cross([0.0, 0.0, 1.0], heading)
        if abs(float(np.dot(d, side))) <= math.sin(snap):
            return math.atan2(d[2], float(np.dot(d, heading))), math.atan2(heading[1], heading[0])
    return math.asin(float(np.clip(d[2], -1, 1))), math.atan2(d[1], d[0])


def child_angles(d, parent_rot, want, tol, snap):
    """(angle, azimuth, turn) rad of a child along ``d`` in its parent's frame (see
    :func:`treeinfer.tree.types.local_rotation`) with its hinge within ``tol`` of ``want``:
    exact when the plane of the two links gives that hinge; for a bend under ``snap`` rad,
    the hinge chosen and the link turned by at most ``snap``; else ``turn`` = the exact (angle,
    azimuth) of a welded connector, and the hinge's azimuth about it."""
    xp, yp, zp = parent_rot[:, 0], parent_rot[:, 1], parent_rot[:, 2]
    dl = parent_rot.T @ d
    a = math.acos(float(np.clip(dl[0], -1.0, 1.0)))
    az = math.atan2(-dl[1], dl[2]) if math.sin(a) > 1e-9 else 0.0
    y_exact = math.cos(az) * yp + math.sin(az) * zp
    w = want - np.dot(want, d) * d
    if np.linalg.norm(w) < 1e-9:
        return a, az, None
    w = w / np.linalg.norm(w)
    if abs(float(np.dot(y_exact, w))) >= math.cos(tol):
        return a, az, None
    if a <= snap:
        proj = w - np.dot(w, xp) * xp
        if np.linalg.norm(proj) > 0.1:
            az2 = math.atan2(float(np.dot(proj, zp)), float(np.dot(proj, yp)))
            yv = math.cos(az2) * yp + math.sin(az2) * zp
            zv = -math.sin(az2) * yp + math.cos(az2) * zp
            if abs(float(np.dot(d, yv))) <= math.sin(snap):
                return math.atan2(float(np.dot(d, zv)), float(np.dot(d, xp))), az2, None
    conn = parent_rot @ local_rotation(
        Branch("x", None, 1.0, 1.0, math.degrees(a), math.degrees(az))
    )
    return 0.0, math.atan2(float(np.dot(w, conn[:, 2])), float(np.dot(w, conn[:, 1]))), (a, az)


def clip_box(box, rng) -> tuple[float, float]:
    lo = min(max(box[0], rng[0]), rng[1] / 2)
    hi = max(min(box[1], rng[1]), lo * 2)
    return (round_sig(lo), round_sig(hi))


def round_sig(v: float) -> float:
    return float(f"{v:.4g}")


def carried_inertia(tree: Tree) -> dict[str, float]:
    """Moment of inertia (kg m^2) about each branch's hinge axis (its frame's y through its
    joint) of the branch and everything it carries, at the rest pose."""
    frames = world_frames(tree)
    per = {}
    for b in tree.branches:
        p, r = frames[b.name]
        m, local_com, local_inertia = branch_inertial(tree, b)
        per[b.name] = (m, p + r @ local_com, r @ local_inertia @ r.T)
    out = {}
    for b in tree.branches:
        p, r = frames[b.name]
        n = r[:, 1]
        stack, total = [b.name], 0.0
        while stack:
            x = stack.pop()
            m, com, inertia = per[x]
            d = com - p
            total += float(n @ inertia @ n) + m * float(d @ d - (d @ n) ** 2)
            stack += list(tree.children(x))
        out[b.name] = total
    return out
