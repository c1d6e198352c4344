"""Pull directions: ``"down"``, ``"horizontal"`` or a world vector, as a unit vector for a tree.

The simulator applies each profile's force along a unit vector ``d`` and measures the
displacement along it (:func:`treeinfer.sim.simulate`, ``direction=``). This module turns the
user-facing spellings (tree file ``pull: {direction: ...}``, per-recording sidecar, CLI
``--direction``) into that vector.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import ConfigError
from ..tree.description import Tree, world_frames

DIRECTION_NAMES = ("down", "horizontal")


def pull_direction(tree: Tree, spec="down", branch: str | None = None) -> np.ndarray:
    """[3] unit world vector of a pull on ``tree``.

    Args:
      spec: ``"down"`` (along gravity: the paper's pull), ``"horizontal"`` (horizontal and
        perpendicular to the grasped branch at its geometric rest direction: ``axis x g_hat``
        normalised, i.e. to the branch's left when looking along it from above; for a vertical
        branch, the base's heading ``(cos yaw, sin yaw, 0)`` projected off gravity, which keeps
        a vertical stem's push in its bending plane), or a world vector ``[x, y, z]`` (any
        length, normalised here), also as a string ``"x,y,z"``.
      branch: the grasped branch (None: the tree's).

    A hinge only turns about its axis: a push along the hinge axes of the grasped branch and
    its ancestors bends nothing (``tau`` stays 0). For a branch forking in a vertical bending
    plane (``azimuth_deg`` 0) that axis is horizontal and across the branch, i.e. exactly
    ``"horizontal"``; a sideways push on such a branch needs joints whose axes are not
    horizontal (branches forking at a non-zero azimuth) or a vertical stem.

    Raises:
      ConfigError: an unknown name, a vector that is not 3 finite numbers or is zero.
    """
    g = np.asarray(tree.gravity, float)
    g_hat = g / np.linalg.norm(g)
    if isinstance(spec, str):
        name = spec.strip().lower()
        if name == "down":
            return g_hat
        if name == "horizontal":
            rot = world_frames(tree)[
                tree.grasp_branch if branch is None else tree.branch(branch).name
            ][1]
            axis = rot[:, 0]
            d = np.cross(axis, g_hat)
            if np.linalg.norm(d) < 1e-9:  # a branch along gravity: push along the base heading
                yaw = math.radians(tree.base_yaw_deg)
                h = np.array([math.cos(yaw), math.sin(yaw), 0.0])
                d = h - (h @ g_hat) * g_hat
                if np.linalg.norm(d) < 1e-9:
                    d = np.cross(g_hat, [0.0, 1.0, 0.0])
            return d / np.linalg.norm(d)
        parts = name.split(",")
        if len(parts) != 3:
            raise ConfigError(
                f"direction: expected 'down', 'horizontal' or a vector 'x,y,z', got {spec!r}"
            )
        spec = parts
    try:
        v = np.asarray([float(x) for x in spec], float)
    except (TypeError, ValueError):
        raise ConfigError(
            f"direction: expected 'down', 'horizontal' or 3 numbers [x, y, z], got {spec!r}"
        ) from None
    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) == 0:
        raise ConfigError(f"direction: must be a finite non-zero vector [x, y, z], got {list(v)}")
    return v / np.linalg.norm(v)
