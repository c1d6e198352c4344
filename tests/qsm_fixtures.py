"""Small synthetic QSMs written in each tool's layout (tests of treeinfer.tree.qsm*).

One tree: a vertical stem of 12 cylinders (0.2 m each, radius 5 -> 3 cm) standing at an
absolute position (10, 20, 100) m, a horizontal branch of 5 cylinders (0.2 m, radius 2 -> 1.2
cm) leaving the 5th stem cylinder's end along +x, and a twig (2 cylinders of 0.1 m, radius 3
mm) leaving the branch's 3rd cylinder's end along +y."""

from __future__ import annotations

from pathlib import Path

import numpy as np

BASE = np.array([10.0, 20.0, 100.0])


def sapling() -> dict[str, np.ndarray]:
    start, end, radius, parent, order = [], [], [], [], []

    def add(s, e, r, p, o):
        start.append(np.asarray(s, float))
        end.append(np.asarray(e, float))
        radius.append(r)
        parent.append(p)
        order.append(o)
        return len(start) - 1

    prev = -1
    stem = []
    for k in range(12):
        s = BASE + [0, 0, 0.2 * k]
        prev = add(s, s + [0, 0, 0.2], 0.05 - 0.02 * k / 11, prev, 0)
        stem.append(prev)
    prev = stem[4]
    branch = []
    for k in range(5):
        s = BASE + [0.2 * k, 0, 1.0]
        prev = add(s, s + [0.2, 0, 0], 0.02 - 0.008 * k / 4, prev, 1)
        branch.append(prev)
    prev = branch[2]
    for k in range(2):
        s = BASE + [0.6, 0.1 * k, 1.0]
        prev = add(s, s + [0, 0.1, 0], 0.003, prev, 2)
    return {
        "start": np.array(start),
        "end": np.array(end),
        "radius": np.array(radius),
        "parent": np.array(parent),  # 0-based, -1 root
        "order": np.array(order),
    }


def _branch_ids(t):
    """A branch id per cylinder (1-based, as TreeQSM numbers them)."""
    return np.where(t["order"] == 0, 1, np.where(t["order"] == 1, 2, 3))


def write_simpleforest(path: Path, t=None, scale: float = 1.0) -> Path:
    t = t or sapling()
    head = (
        "ID, parentID, startX, startY, startZ, endX, endY, endZ, radius, length, growthLength, "
        "averagePointDistance,segmentID, parentSegmentID, branchOrder, reverseBranchOrder, "
        "branchID"
    )
    lines = [head]
    for i in range(len(t["radius"])):
        s, e = t["start"][i] * scale, t["end"][i] * scale
        ln = float(np.linalg.norm(e - s))
        lines.append(
            ",".join(
                str(v)
                for v in (
                    i, t["parent"][i], *s, *e, t["radius"][i] * scale, ln, 1.0, 0.001,
                    _branch_ids(t)[i], 0, t["order"][i], 1, 0,
                )
            )
        )  # fmt: skip
    path.write_text("\n".join(lines) + "\n")
    return path


def write_archi(path: Path, t=None) -> Path:
    t = t or sapling()
    head = (
        "startX,startY,startZ,endX,endY,endZ,cyl_ID,parent_ID,extension_ID,radius_cyl,length,"
        "volume,axis_ID,segment_ID,node_ID,branching_order"
    )
    lines = [head]
    for i in range(len(t["radius"])):
        s, e = t["start"][i], t["end"][i]
        ln = float(np.linalg.norm(e - s))
        r = t["radius"][i]
        lines.append(
            ",".join(
                str(v)
                for v in (
                    *s, *e, i + 1, t["parent"][i] + 1, 0, r, ln, np.pi * r * r * ln,
                    _branch_ids(t)[i], 1, 0, t["order"][i] + 1,
                )
            )
        )  # fmt: skip
    path.write_text("\n".join(lines) + "\n")
    return path


def _treeqsm_rows(t):
    axis = t["end"] - t["start"]
    length = np.linalg.norm(axis, axis=1)
    axis = axis / length[:, None]
    return axis, length


def write_treeqsm_v24(path: Path, t=None) -> Path:
    t = t or sapling()
    axis, length = _treeqsm_rows(t)
    names = [
        "radius (m)", "length (m)", "start_point", "axis_direction", "parent", "extension",
        "branch", "branch_order", "position_in_branch", "mad", "SurfCov", "added",
        "UnmodRadius (m)",
    ]  # fmt: skip
    lines = ["\t".join(names)]
    for i in range(len(t["radius"])):
        row = (
            t["radius"][i], length[i], *t["start"][i], *axis[i], t["parent"][i] + 1, 0,
            _branch_ids(t)[i], t["order"][i], 1, 0.001, 1.0, 0, t["radius"][i],
        )  # fmt: skip
        lines.append("\t".join(f"{v:g}" if isinstance(v, float) else str(v) for v in row))
    path.write_text("\n".join(lines) + "\n")
    return path


def write_treeqsm_v23(path: Path, t=None, mat_order: bool = False) -> Path:
    """Headerless, 15 columns, CRLF; ``mat_order``: added and UnmodRadius before branch."""
    t = t or sapling()
    axis, length = _treeqsm_rows(t)
    lines = []
    for i in range(len(t["radius"])):
        head = (t["radius"][i], length[i], *t["start"][i], *axis[i], t["parent"][i] + 1, 0)
        ints = (_branch_ids(t)[i], t["order"][i], 1)
        tail = (0, t["radius"][i])
        row = head + (tail + ints if mat_order else ints + tail)
        lines.append("\t".join(repr(float(v)) for v in row))
    path.write_bytes(("\r\n".join(lines) + "\r\n").encode())
    return path


def write_treeqsm_mat(path: Path, t=None) -> Path:
    import scipy.io

    t = t or sapling()
    axis, length = _treeqsm_rows(t)
    cyl = {
        "radius": t["radius"],
        "length": length,
        "start": t["start"],
        "axis": axis,
        "parent": (t["parent"] + 1).astype(np.uint16),
        "extension": np.zeros(len(length), np.uint16),
        "branch": _branch_ids(t).astype(np.uint8),
        "BranchOrder": t["order"].astype(np.uint8),
    }
    scipy.io.savemat(path, {"QSM": {"cylinder": cyl}})
    return path


WRITERS = {
    "simpleforest": write_simpleforest,
    "archi": write_archi,
    "treeqsm-v24": write_treeqsm_v24,
    "treeqsm-v23": write_treeqsm_v23,
    "treeqsm-mat": write_treeqsm_mat,
}
SUFFIX = {"treeqsm-mat": ".mat", "treeqsm-v24": ".txt", "treeqsm-v23": ".txt"}
