"""Checks on resolved pulls (:class:`treeinfer.data.pulls.ResolvedPull`: branch, fraction, unit
direction, label): can the pull bend a hinge of the model, and is a prediction made at the
recording's own pull. Re-exported by :mod:`treeinfer.data.pulls`."""

from __future__ import annotations

import numpy as np


def pull_leverage(tree, pull) -> float:
    """Largest joint torque per newton [m] the pull exerts at the rest geometry (metres).

    Each jointed branch on the path to the root is a hinge about its frame's y-axis at its
    joint; a pull ``F d`` at the grasp point C exerts ``axis . ((C - joint) x d)`` on it. Zero
    means the direction runs along every hinge axis (or through every joint): the hinge model
    cannot move under it (e.g. a horizontal push across a branch whose hinges all bend in its
    vertical plane)."""
    from ..tree.description import world_frames

    frames = world_frames(tree)
    origin, rot = frames[pull.branch]
    c = origin + rot[:, 0] * pull.fraction * tree.branch(pull.branch).length
    best = 0.0
    for name in tree.ancestors(pull.branch):
        if tree.branch(name).fixed:
            continue
        o, r = frames[name]
        best = max(best, abs(float(r[:, 1] @ np.cross(c - o, pull.direction))))
    return best


def check_pull_moves(tree, pull, what: str = "pull", rtol: float = 1e-6):
    """A message if ``pull`` cannot bend any hinge of the model (see :func:`pull_leverage`),
    else ``None``; callers refuse the data set or warn."""
    scale = max(tree.total_length(), 1e-12)
    if pull_leverage(tree, pull) > rtol * scale:
        return None
    return (
        f"{what}: a pull {pull.label} on branch '{pull.branch}' acts along the axes of all its "
        "hinges (each branch bends about one axis only), so the model predicts no displacement; "
        "pull in the branches' bending plane, or give the tree joints that bend that way"
    )


def check_same_pull(
    recorded,
    predicted,
    what: str = "recording",
    fraction_tol: float = 1e-6,
    cos_tol: float = 1e-6,
) -> str | None:
    """``None`` if ``predicted`` is at the recording's grasp point and direction, else a message
    saying how they differ (for ``predict``/``evaluate`` to refuse or warn)."""
    diffs = []
    if recorded.branch != predicted.branch:
        diffs.append(f"branch '{predicted.branch}' instead of '{recorded.branch}'")
    elif abs(recorded.fraction - predicted.fraction) > fraction_tol:
        diffs.append(f"fraction {predicted.fraction:g} instead of {recorded.fraction:g}")
    cos = float(np.dot(recorded.direction, predicted.direction))
    if cos < 1.0 - cos_tol:
        diffs.append(f"direction {predicted.label} instead of {recorded.label}")
    if not diffs:
        return None
    return (
        f"{what}: the prediction is for a pull at {', '.join(diffs)}; its displacement is not "
        "comparable with the recording's"
    )
