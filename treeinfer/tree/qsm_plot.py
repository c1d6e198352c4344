"""The QSM with the converted tree drawn over it: cylinders (grey; line width grows with the
radius; pale where lumped or dropped), links (red: inferred joints; blue: fixed gains), the
centres of the masses lumped into links (green, size by mass), joints (black dots) and the
grasp point (star), in two side views (x-z and y-z, base at the origin, metres)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .qsm_convert import QsmTree
from .types import world_frames


def plot_qsm(result: QsmTree, axes=None):
    """Draw ``result`` (from :func:`treeinfer.tree.qsm_convert.tree_from_qsm`); returns
    ``(fig, axes)`` (two axes: front x-z and side y-z). Pass ``axes`` (two) to draw into
    existing ones."""
    import matplotlib.pyplot as plt

    if axes is None:
        fig, axes = plt.subplots(1, 2, figsize=(11, 6), sharey=True)
    else:
        fig = axes[0].figure
    cyl = result.cylinders
    start, end = cyl.start - result.origin, cyl.end - result.origin
    width = 0.4 + 40.0 * cyl.radius / max(float(cyl.radius.max()), 1e-9)
    frames = world_frames(result.tree)
    tree = result.tree
    lump_max = max((b.lump.mass for b in tree.branches if b.lump is not None), default=0.0)
    for ax, (i, j), label in zip(axes, ((0, 2), (1, 2)), ("x (m)", "y (m)")):
        for used, colour, alpha in ((False, "0.75", 0.6), (True, "0.45", 0.9)):
            sel = np.flatnonzero(result.in_links == used)
            for c in sel:
                ax.plot(
                    [start[c, i], end[c, i]],
                    [start[c, j], end[c, j]],
                    color=colour,
                    lw=width[c] * 0.25,
                    alpha=alpha,
                    solid_capstyle="butt",
                )
        for b in tree.branches:
            p, r = frames[b.name]
            q = p + r[:, 0] * b.length
            if not b.fixed:
                colour = "tab:red" if b.name in tree.inferred else "tab:blue"
                ax.plot([p[i], q[i]], [p[j], q[j]], color=colour, lw=2.0)
                ax.plot(p[i], p[j], "o", color="k", ms=4)
            if b.lump is not None:  # its centre, tied to the link's middle
                c = p + r @ np.asarray(b.lump.com)
                mid = p + r[:, 0] * b.length / 2
                ax.plot([mid[i], c[i]], [mid[j], c[j]], ls="--", color="tab:green", lw=1.2)
                ms = 5 + 10 * np.sqrt(b.lump.mass / max(lump_max, 1e-12))
                ax.plot(c[i], c[j], "o", color="tab:green", mec="k", ms=ms, alpha=0.8)
        gb = tree.branch(tree.grasp_branch)
        p, r = frames[gb.name]
        gp = p + r[:, 0] * gb.length * tree.grasp_fraction
        ax.plot(gp[i], gp[j], "*", color="gold", mec="k", ms=14)
        ax.set_xlabel(label)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("z (m)")
    rep = result.report
    axes[0].set_title("front (x-z)")
    axes[1].set_title("side (y-z)")
    fig.suptitle(
        f"{Path(rep['source']).name} ({rep['format']}): {rep['cylinders']} cylinders -> "
        f"{rep['links']} links, {rep['inferred']} inferred joints (red), grasp * on "
        f"'{tree.grasp_branch}'",
        fontsize=10,
    )
    from matplotlib.lines import Line2D

    handles = [
        Line2D([], [], color="0.45", lw=3, label="QSM cylinders in links"),
        Line2D([], [], color="0.75", lw=3, label="QSM cylinders lumped / dropped"),
        Line2D([], [], color="tab:red", lw=2, label="link, inferred joint"),
        Line2D([], [], color="tab:blue", lw=2, label="link, fixed gains"),
        Line2D([], [], color="tab:green", marker="o", ls="--", label="lumped mass (in its link)"),
        Line2D([], [], color="k", marker="o", ls="", label="joint"),
        Line2D([], [], color="gold", mec="k", marker="*", ms=12, ls="", label="grasp"),
    ]
    axes[1].legend(handles=handles, loc="best", fontsize=8)
    fig.tight_layout()
    return fig, axes
