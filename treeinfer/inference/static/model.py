"""How a run maps its particles to predicted displacements: :class:`Model`.

A model is the kind (the dynamic rollout or the static equilibria), the theta layout (which
gains are inferred) and the pulls (grasped branch and direction per force profile). The
paper's model -- dynamic, ``[log Kp, log Kd]``, every pull down at the tree's grasp branch --
is represented by ``None`` throughout the package so that its runs stay exactly as before.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import ConfigError
from ...sim import Simulator, simulate
from .equilibrium import static_rollout
from .layout import ParameterLayout, parse_model_kind, run_tree, tree_layout


class Model(NamedTuple):
    """How a run maps its particles to predicted displacements.

    Attributes:
        kind: ``"dynamic"`` (time-stepped rollout) or ``"static"`` (:func:`static_rollout`).
        layout: the theta layout (:func:`tree_layout`).
        tree: the tree (lengths of grasped branches, pull directions).
        direction: None (along gravity) or [3] / [B, 3] world vectors.
        grasp_branch: None (the tree's grasp branch) or B branch names.
    """

    kind: str
    layout: ParameterLayout
    tree: object = None
    direction: object = None
    grasp_branch: object = None

    @property
    def labels(self) -> tuple[str, ...]:
        return tuple(self.layout.labels)

    @property
    def is_paper(self) -> bool:
        """Dynamic, Kp and Kd inferred, every pull along gravity at the tree's grasp branch."""
        return (
            self.kind == "dynamic"
            and self.layout.infers_damping
            and self.direction is None
            and self.grasp_branch is None
        )


def model_for(tree, model_kind: str = "dynamic", direction=None, grasp_branch=None) -> Model:
    """The :class:`Model` of a run from its tree and ``--model-kind``. Both kinds pull along
    ``direction`` (default: the tree file's ``pull.direction``, resolved on the grasp branch by
    :func:`treeinfer.data.pulls.pull_direction`; the dynamic model keeps None, i.e. along gravity,
    for the default ``down``)."""
    kind = parse_model_kind(model_kind)
    tree = run_tree(tree, kind)
    spec = getattr(tree, "pull_direction", "down")
    if direction is None and (kind == "static" or spec != "down"):
        from ...data.pulls import pull_direction

        direction = pull_direction(tree, tree.grasp_branch, spec)
    if grasp_branch is not None and not isinstance(grasp_branch, str):
        grasp_branch = tuple(str(b) for b in grasp_branch)
    return Model(kind, tree_layout(tree), tree, direction, grasp_branch)


@partial(jax.jit, static_argnums=(0, 6))
def _dynamic_rollout(sim, kp, kd, forces, grasp_fraction, direction, grasp_branch):
    return simulate(
        sim, kp, kd, forces, grasp_fraction, direction=direction, grasp_branch=grasp_branch
    )


def model_rollout(sim: Simulator, model: Model | None, theta, forces, grasp_fraction=None):
    """Predicted :class:`~treeinfer.sim.Rollout` [P, B, T] of particles ``theta [P, D]`` (the
    model's layout; the full ``[log Kp, log Kd]`` when ``model`` is None) under ``forces
    [B, T]`` N, each profile at its own grasped branch and direction (the model's). The dynamic
    model runs :func:`treeinfer.sim.simulate` (jitted), the static one :func:`static_rollout`
    (Kd plays no role there)."""
    theta = jnp.atleast_2d(jnp.asarray(theta))
    if model is None:
        r = sim.n_joints
        return simulate(
            sim, jnp.exp(theta[..., :r]), jnp.exp(theta[..., r : 2 * r]), forces, grasp_fraction
        )
    kp, kd = model.layout.gains(theta)
    if model.kind == "static":
        return static_rollout(
            sim, kp, forces, grasp_fraction, model.direction, model.grasp_branch, model.tree
        )
    branch = model.grasp_branch
    branch = tuple(branch) if branch is not None and not isinstance(branch, str) else branch
    direction = None if model.direction is None else jnp.asarray(model.direction, sim.dtype)
    frac = None if grasp_fraction is None else jnp.asarray(grasp_fraction, sim.dtype)
    return _dynamic_rollout(sim, kp, kd, jnp.asarray(forces), frac, direction, branch)


def model_with_pulls(
    model: Model | None, data_dir, sources: Sequence[str], grasp_fraction=None, tree=None
):
    """The model with each recording's own pull from ``data_dir``'s ``pulls.yaml`` (grasped
    branch, grasp point, direction: :func:`treeinfer.data.pulls.load_data_pulls`).

    Args:
        model: the run's model; None (the paper's dynamic model) needs ``tree``.
        sources: the trajectories' file names, in stacked order.
        grasp_fraction: an explicit ``--grasp-fraction`` (overrides the files' points).
        tree: the run's tree, for ``model=None``.

    Returns:
        (model, grasp fractions [B] or ``grasp_fraction``). The model unchanged (and
        ``grasp_fraction``) when the folder has no ``pulls.yaml``; ``None`` stays ``None`` when
        every recording was pulled down at the tree's grasp branch.
    """
    from ...data.pulls import PULLS_FILE, check_pull_moves, load_data_pulls, stack_resolved

    if data_dir is None or (model is None and tree is None):
        return model, grasp_fraction
    if not (Path(data_dir) / PULLS_FILE).is_file():
        return model, grasp_fraction
    base = model_for(tree, "dynamic") if model is None else model
    resolved = load_data_pulls(data_dir, base.tree, [Path(s).name for s in sources])
    for name, r in zip(sources, resolved):
        stuck = check_pull_moves(base.tree, r, f"{Path(data_dir) / PULLS_FILE}: {Path(name).name}")
        if stuck is not None:
            raise ConfigError(stuck)
    branches, fractions, directions = stack_resolved(resolved, base.tree)
    own = fractions if grasp_fraction is None else grasp_fraction
    if model is None:
        from ...data.pulls import pull_direction

        down = pull_direction(base.tree, base.tree.grasp_branch, "down")
        if all(b == base.tree.grasp_branch for b in branches) and np.allclose(
            directions @ down, 1.0, atol=1e-9
        ):
            return None, own
    return base._replace(direction=directions, grasp_branch=tuple(branches)), own
