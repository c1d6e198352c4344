"""Stiffness tied along a stem's taper: one free scale (hard tie) or a scale plus per-joint
deviations with a Normal prior (soft tie).

For a tapered stem modelled as a chain of hinges, a beam piece of length ``l`` and radius ``r``
bends like a hinge of stiffness ``E I / l`` with ``I = pi r^4 / 4``; with E unknown but the taper
known, the hinges' stiffnesses are tied, ``Kp_j = s * shape_j``, and only the scale ``s`` is
inferred (``theta = [log s]``, plus noise columns). Two push heights identify one scale where
they cannot identify three free stiffnesses.

A hard tie trusts the taper (and the hinge model) exactly, so the band of a prediction at an
untested height carries none of the model's error. The **soft tie**

    log Kp_j = log s + log shape_j + delta_j,      delta_j ~ Normal(0, tau)

(``theta = [log s, delta_1..R]``, labels ``Kp_scale``, ``Kp_taper_ratio[joint]``: reports show
``exp`` of each column, the scale in N m/rad and each joint's ratio to the taper) keeps the
taper as the prior's centre but lets each joint deviate by about ``tau`` (natural-log units:
``tau = 0.1`` is about 10%); the data pin the combinations of deltas that the tested heights
see, and the others keep their prior spread, so
an extrapolation's band widens where the data say nothing.

:func:`taper_shape` reads the shape from the tree's branches (Hencky bar-chain lumping: each
hinge carries the flexibility of the half-bars on either side of it, :func:`taper_shape`).
``inference: {tie: shape, tie_shape: [...]}`` gives the shape explicitly instead (e.g. the
beam-matched shape that ``treeinfer tree --kind stem`` writes,
:func:`treeinfer.tree.stem.matched_hinges`): ``Kp_j = s * tie_shape_j`` exactly, as given
(not rescaled), hard or soft (``tie_scale``) as for the taper.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ...errors import ConfigError


class TiedLayout(NamedTuple):
    """``log Kp_j = theta[0] + log shape[j] (+ theta[1 + j] when soft)``; damping held at
    ``fixed_kd`` [R] N m s/rad.

    Duck-types :class:`~treeinfer.inference.static.ParameterLayout` (``dim``, ``labels``, ``gains``,
    ``full_theta``, ``theta``, ``lower``/``upper`` in log units) and adds :meth:`log_prior`
    (the box on the scale, Normal(0, tau) on the deviations).
    """

    joints: tuple[str, ...]
    shape: np.ndarray  # [R] dimensionless, Kp_j / s
    fixed_kd: np.ndarray  # [R] N m s/rad
    lower: np.ndarray  # [D] log of the scale's prior box (then -4 tau per deviation)
    upper: np.ndarray  # [D]
    parameters: tuple[str, ...] = ("kp",)
    label: str = "Kp_scale"
    tau: float | None = None  # None: hard tie; else the deviations' std (log units)
    tie: str = "taper"

    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def soft(self) -> bool:
        return self.tau is not None

    @property
    def dim(self) -> int:
        return 1 + (self.n_joints if self.soft else 0)

    @property
    def infers_damping(self) -> bool:
        return False

    @property
    def labels(self) -> list[str]:
        return [self.label] + ([f"Kp_taper_ratio[{n}]" for n in self.joints] if self.soft else [])

    def gains(self, theta):
        """``theta [..., D+]`` -> (Kp [..., R], Kd [..., R]) in natural units (jax)."""
        theta = jnp.asarray(theta)
        log_kp = theta[..., :1] + jnp.log(jnp.asarray(self.shape, theta.dtype))
        if self.soft:
            log_kp = log_kp + theta[..., 1 : 1 + self.n_joints]
        kp = jnp.exp(log_kp)
        kd = jnp.broadcast_to(jnp.asarray(self.fixed_kd, kp.dtype), kp.shape)
        return kp, kd

    def theta(self, kp, kd=None) -> np.ndarray:
        """Inverse of :meth:`gains` (numpy): ``kp [..., R]`` -> ``[..., D]``. The scale is the
        geometric mean of ``kp / shape``; a hard tie keeps only it (the least-squares fit in log
        units), a soft tie keeps the residuals as the deviations."""
        resid = np.log(np.asarray(kp, float)) - np.log(self.shape)
        scale = resid.mean(axis=-1, keepdims=True)
        return np.concatenate([scale, resid - scale], axis=-1) if self.soft else scale

    def full_theta(self, theta):
        """``[..., D]`` -> ``[..., 2R]`` (log Kp, log Kd)."""
        kp, kd = self.gains(theta)
        return jnp.concatenate([jnp.log(kp), jnp.log(kd)], axis=-1)

    def log_prior(self, prior_sigma: float, prior_space: str = "log"):
        """``theta [P, D] -> [P]``: the smoothed box on the scale (log-uniform inside, as every
        gain's prior; ``prior_sigma`` the tails' share of its width) plus, soft, the
        deviations' ``Normal(0, tau)`` (numpyro) log-density."""
        from numpyro.distributions import Normal

        from ...model.priors import smoothed_box

        lo, hi = float(self.lower[0]), float(self.upper[0])
        if prior_space == "log":
            box = smoothed_box([lo], [hi], prior_sigma * (hi - lo))
            scale_prior = lambda th: box(th[..., :1])  # noqa: E731
        elif prior_space == "linear":
            elo, ehi = math.exp(lo), math.exp(hi)
            box = smoothed_box([elo], [ehi], prior_sigma * (ehi - elo))
            scale_prior = lambda th: box(jnp.exp(th[..., :1])) + th[..., 0]  # noqa: E731
        else:
            raise ConfigError(f"prior_space: expected 'log' or 'linear', got {prior_space!r}")
        if not self.soft:
            return scale_prior
        normal = Normal(0.0, float(self.tau))
        r = self.n_joints
        return lambda th: scale_prior(th) + jnp.sum(normal.log_prob(th[..., 1 : 1 + r]), -1)


def taper_shape(tree) -> np.ndarray:
    """[R] relative stiffnesses of ``tree``'s inferred joints along their stem (max 1).

    Hencky bar-chain lumping: the hinge at the base of branch ``b`` carries the bending
    flexibility of the beam from the middle of the bar below it to the middle of ``b``, each
    half-bar a uniform cylinder of its own radius (``1/K = sum l / (E pi r^4 / 4)``). Below, a
    whole welded (``fixed``) parent is taken (the bar down to the clamp) and nothing when ``b``
    is the root; above, the whole of ``b`` when no jointed branch grows from it (the free
    end). For equal segments of a slowly varying taper this is ``E I(z_j) / l`` at hinge j.
    """
    out = []
    for name in tree.inferred:
        b = tree.branch(name)
        pieces = []
        if b.parent is not None:
            p = tree.branch(b.parent)
            pieces.append((p.length if p.fixed else 0.5 * p.length, p.radius))
        top = not any(not tree.branch(c).fixed for c in tree.children(name))
        pieces.append((b.length if top else 0.5 * b.length, b.radius))
        out.append(1.0 / sum(length / r**4 for length, r in pieces))
    shape = np.asarray(out, float)
    return shape / shape.max()


def tied_layout(tree, shape, scale_bounds, fixed_kd=None, tau=None) -> TiedLayout:
    """:class:`TiedLayout` for ``tree``'s inferred joints.

    Args:
        shape: [R] positive relative stiffnesses (``Kp_j = s * shape_j``), order
            ``tree.inferred``.
        scale_bounds: (low, high) prior box of the scale s (log-uniform inside).
        fixed_kd: [R] or scalar N m s/rad (default the geometric mean of each Kd box).
        tau: None (hard tie) or the std of each joint's log-stiffness about the taper (> 0).
    """
    joints = tuple(tree.inferred)
    shape = np.asarray(shape, float).reshape(-1)
    if shape.shape != (len(joints),) or not np.all(np.isfinite(shape)) or np.any(shape <= 0):
        raise ConfigError(f"shape: expected {len(joints)} positive numbers, got {shape.tolist()}")
    lo, hi = (float(v) for v in scale_bounds)
    if not (0 < lo < hi < np.inf):
        raise ConfigError(f"scale_bounds: expected 0 < low < high, got {scale_bounds!r}")
    if tau is not None and not (math.isfinite(float(tau)) and float(tau) > 0):
        raise ConfigError(f"tie_scale: expected a positive number, got {tau!r}")
    if fixed_kd is None:
        kd = np.asarray([tree.bounds[n].kd for n in joints], float)
        fixed = np.sqrt(kd[:, 0] * kd[:, 1])
    else:
        fixed = np.broadcast_to(np.asarray(fixed_kd, float), (len(joints),)).copy()
    lower, upper = [math.log(lo)], [math.log(hi)]
    if tau is not None:  # the deviations' box only sets where uniform starts are drawn
        lower += [-4.0 * float(tau)] * len(joints)
        upper += [4.0 * float(tau)] * len(joints)
    return TiedLayout(
        joints,
        shape,
        fixed,
        np.asarray(lower),
        np.asarray(upper),
        tau=None if tau is None else float(tau),
    )


def tree_tie_shape(tree) -> np.ndarray:
    """[R] the tied shape of ``tree``'s inferred joints: :func:`taper_shape` for ``tie: taper``,
    the file's ``inference.tie_shape`` for ``tie: shape``.

    Raises:
        ConfigError: ``tie: shape`` without a shape (e.g. ``--tie shape`` on a tree file that
            has no ``inference.tie_shape``), or no tie at all.
    """
    if tree.tie == "taper":
        return taper_shape(tree)
    if tree.tie == "shape":
        shape = getattr(tree, "tie_shape", None)
        if shape is None or len(shape) != len(tree.inferred):
            raise ConfigError(
                "inference.tie: 'shape' needs inference.tie_shape in the tree file, one positive "
                f"number per inferred joint ({', '.join(tree.inferred)}); "
                "`treeinfer tree --kind stem` writes one"
            )
        return np.asarray(shape, float)
    raise ConfigError(f"inference.tie: no stiffness tie on this tree (got {tree.tie!r})")


def tree_tied_layout(tree, fixed_kd) -> TiedLayout:
    """The layout of a tree file's ``inference: {tie: taper|shape[, tie_scale: TAU]}``: the
    shape from :func:`tree_tie_shape`, the scale's box wide enough for every joint's own Kp box
    (``[min_j lo_j / shape_j, max_j hi_j / shape_j]``).

    Raises:
        ConfigError: the tree infers damping (the tie is on stiffness only); ``tie: shape``
            without its shape.
    """
    if "kd" in tuple(tree.parameters):
        raise ConfigError(
            f"inference.tie: '{tree.tie}' ties stiffness only, but this run also infers damping; "
            "add 'parameters: [kp]' to the tree file's inference section or run "
            "--model-kind static"
        )
    shape = tree_tie_shape(tree)
    lo, hi = tree.bounds_array()
    r = len(tree.inferred)
    bounds = (float(np.min(lo[:r] / shape)), float(np.max(hi[:r] / shape)))
    return tied_layout(tree, shape, bounds, fixed_kd, tau=tree.tie_scale)._replace(tie=tree.tie)


def tied_noise_theta(theta, n_joints: int, settings: dict) -> np.ndarray:
    """A tied run's draws ``theta [N, D]`` (``[log s, (delta_1..R,) noise...]``) laid out as
    :func:`treeinfer.model.gains.noise_params_from_theta` reads them, ``[N, 2R + E]``: the gain
    columns zeroed (unused there), the E noise columns kept. ``settings``: the run's problem
    settings (``kp_shape`` marks a tied layout, ``tie_scale`` None a hard one).

    Without this the per-joint reading (``2R`` gain columns) takes a tied run's deviations for
    noise columns and the predictive band silently loses its noise term."""
    theta = np.atleast_2d(np.asarray(theta, float))
    n_layout = 1 + (n_joints if settings.get("tie_scale") is not None else 0)
    if theta.shape[-1] < n_layout:
        raise ConfigError(
            f"theta: a tied run of {n_joints} joints has at least {n_layout} columns, "
            f"got {theta.shape[-1]}"
        )
    gains = np.zeros(theta.shape[:-1] + (2 * n_joints,))
    return np.concatenate([gains, theta[..., n_layout:]], axis=-1)
