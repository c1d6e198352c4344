"""Which gains a run infers (theta layout) and the model kinds (dynamic rollout or static)."""

from __future__ import annotations

import math
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ...errors import ConfigError
from ...tree.description import PARAMETERS, parse_parameters

MODEL_KINDS = ("dynamic", "static")


class ParameterLayout(NamedTuple):
    """Which gains the samplers move, and how ``theta`` maps to (Kp, Kd).

    ``theta = [log Kp_1..R]`` (+ ``[log Kd_1..R]`` when ``"kd"`` is inferred); a gain that is
    not inferred is held at ``fixed_kd`` [R] N m s/rad.
    """

    parameters: tuple[str, ...]
    joints: tuple[str, ...]
    fixed_kd: np.ndarray
    lower: np.ndarray  # [D] log units
    upper: np.ndarray  # [D] log units

    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def dim(self) -> int:
        return len(self.parameters) * self.n_joints

    @property
    def infers_damping(self) -> bool:
        return "kd" in self.parameters

    @property
    def labels(self) -> list[str]:
        out = [f"Kp[{n}]" for n in self.joints]
        if self.infers_damping:
            out += [f"Kd[{n}]" for n in self.joints]
        return out

    def gains(self, theta):
        """``theta [..., D]`` -> (Kp [..., R], Kd [..., R]) in natural units (jax)."""
        r = self.n_joints
        kp = jnp.exp(theta[..., :r])
        if self.infers_damping:
            kd = jnp.exp(theta[..., r : 2 * r])
        else:
            kd = jnp.broadcast_to(jnp.asarray(self.fixed_kd, kp.dtype), kp.shape)
        return kp, kd

    def theta(self, kp, kd=None) -> np.ndarray:
        """Inverse of :meth:`gains` (numpy); ``kd`` is needed only when it is inferred."""
        kp = np.asarray(kp, float)
        parts = [np.log(kp)]
        if self.infers_damping:
            if kd is None:
                raise ConfigError("theta: Kd is inferred in this layout; give kd")
            parts.append(np.log(np.asarray(kd, float)))
        return np.concatenate(parts, axis=-1)

    def full_theta(self, theta):
        """``[..., D]`` -> the full ``[..., 2R]`` (log Kp, log Kd) layout other code expects."""
        if self.infers_damping:
            return theta
        kd = jnp.broadcast_to(
            jnp.log(jnp.asarray(self.fixed_kd, theta.dtype)), theta.shape[:-1] + (self.n_joints,)
        )
        return jnp.concatenate([theta, kd], axis=-1)


def parameter_layout(tree, parameters=PARAMETERS, fixed_kd=None) -> ParameterLayout:
    """Theta layout for ``tree``'s inferred joints.

    Args:
        parameters: ``("kp",)`` (stiffness only) or ``("kp", "kd")``.
        fixed_kd: [R] or scalar N m s/rad held when Kd is not inferred; default the geometric
            mean of each joint's Kd prior bounds (it matters only for dynamic models).
    """
    params = parse_parameters(list(parameters))
    joints = tuple(tree.inferred)
    kd_bounds = np.asarray([tree.bounds[n].kd for n in joints], float)
    if fixed_kd is None:
        fixed = np.sqrt(kd_bounds[:, 0] * kd_bounds[:, 1])
    else:
        fixed = np.broadcast_to(np.asarray(fixed_kd, float), (len(joints),)).copy()
        if not np.all(np.isfinite(fixed)) or np.any(fixed <= 0):
            raise ConfigError(f"fixed_kd: must be finite and positive, got {fixed.tolist()}")
    lo, hi = tree.bounds_array()
    keep = slice(0, len(joints)) if params == ("kp",) else slice(0, 2 * len(joints))
    return ParameterLayout(params, joints, fixed, np.log(lo[keep]), np.log(hi[keep]))


def damping_note(layout: ParameterLayout | None = None, model_kind: str = "static") -> str:
    """The line a report prints about damping when it is not identified."""
    if model_kind == "static":
        return (
            "damping (Kd): not identified (static model: equilibria carry no damping information)"
        )
    if layout is not None and not layout.infers_damping:
        vals = ", ".join(f"{v:.3g}" for v in layout.fixed_kd)
        return f"damping (Kd): not inferred, held at [{vals}] N m s/rad"
    return ""


def parse_model_kind(value, source: str = "--model-kind") -> str:
    """``dynamic`` (the rollout, the default) or ``static`` (equilibria, stiffness only)."""
    kind = "dynamic" if value is None else str(value).strip().lower()
    if kind not in MODEL_KINDS:
        raise ConfigError(f"{source}: expected one of {', '.join(MODEL_KINDS)}, got {value!r}")
    return kind


def run_tree(tree, model_kind: str = "dynamic"):
    """The tree a run infers: with the static model, stiffness only (``parameters: [kp]``), so
    that the run folder's ``tree.yaml`` and its parameter labels say what was inferred."""
    import dataclasses

    if parse_model_kind(model_kind) == "static" and tuple(tree.parameters) != ("kp",):
        return dataclasses.replace(tree, parameters=("kp",))
    return tree


def tree_layout(tree):
    """:func:`parameter_layout` of ``tree.parameters``; damping, when not inferred, is held at
    each joint's own ``kd`` in the tree file where given, else at its prior box's geometric
    mean. A tree with ``inference: {tie: taper}`` gets the tied layout
    (:func:`treeinfer.inference.static.tied.tree_tied_layout`: one stiffness scale, or soft)."""
    joints = tuple(tree.inferred)
    lo, hi = (np.asarray([tree.bounds[n].kd[i] for n in joints], float) for i in (0, 1))
    own = [tree.branch(n).kd for n in joints]
    fixed = np.asarray([k if k is not None else math.sqrt(a * b) for k, a, b in zip(own, lo, hi)])
    if getattr(tree, "tie", None) is not None:
        from .tied import tree_tied_layout

        return tree_tied_layout(tree, fixed)
    return parameter_layout(tree, getattr(tree, "parameters", PARAMETERS), fixed_kd=fixed)


def with_tie(tree, tie=None, tie_scale=None):
    """``tree`` with a run's ``--tie``/``--tie-scale`` applied over its file's
    ``inference.tie``/``tie_scale`` (``--tie none`` drops the file's tie; ``--tie-scale`` alone
    softens the file's tie), validated: the tie's name, the tree's shape
    (:func:`treeinfer.tree.description.check_tie`) and the layout (no damping inferred).

    Raises:
        ConfigError: naming the flag or the tree file's field.
    """
    import dataclasses

    from ...errors import TreeFileError
    from ...tree.description import check_tie
    from ...tree.types import parse_tie

    if tie is None and tie_scale is None:
        if tree.tie is not None:
            tree_layout(tree)
        return tree
    flags = ("--tie", "--tie-scale")
    name, _ = parse_tie(tie, None, "", flags)
    if tie is None:  # --tie-scale alone: the tree file's tie, softened
        name = tree.tie
    if name is None and tie_scale is not None:
        raise ConfigError(
            "--tie-scale: given without a tie; add --tie taper (or tie: taper to the tree file's "
            "inference section)"
        )
    name, tau = parse_tie(name, tie_scale, "", flags)
    if tie_scale is None and tie is not None and name == tree.tie:
        tau = tree.tie_scale  # --tie taper on a tree that already ties: keep its scale
    out = dataclasses.replace(tree, tie=name, tie_scale=tau)
    if name is not None:
        try:
            check_tie(out)
        except TreeFileError as e:
            raise ConfigError(f"--tie {name}: {e}") from None
        tree_layout(out)
    return out
