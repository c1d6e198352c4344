"""The simulator's data types and defaults: :class:`Rollout`, :class:`Simulator` (built by
:func:`treeinfer.sim.make_simulator`) and the step-size constants.

A :class:`Simulator` is a static argument of the jitted :func:`treeinfer.sim.simulate`. It is
hashed and compared by its *content* (the compiled MuJoCo model's bytes and every field), so two
simulators built from the same tree with the same settings share one compiled program: a second
``simulate`` call, or a second ``treeinfer simulate`` in the same process, does not recompile.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
from dataclasses import dataclass, field, fields
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import mjx as _mjx_backend

BACKENDS = ("auto", "fused", "mjx", "pallas")
DEFAULT_MAX_SIM_DT = 0.005  # s: upper bound on the simulation step whatever the prior
FORCE_INTERPS = ("linear", "hold")
DEFAULT_SIM_TOLERANCE = 1e-4  # m: default accuracy target of the step when the noise is unknown
STABILITY_MARGIN = 1.5  # require omega_max * dt <= this (explicit-spring limit is 2)
PRIOR_STIFFNESS_HEADROOM = 2.0  # particles may wander a little past the prior box's upper Kp


class Rollout(NamedTuple):
    """Simulator output.

    Attributes:
      tau: [P, B, T] m, displacement of the grasp point from its settled rest along the pull
        direction (positive downward for the default pull along gravity).
      tau_dot: [P, B, T] m/s, its time derivative.
      stable: [P, B] bool; False where the rollout blew up (tau, tau_dot are zero there).
    """

    tau: jax.Array
    tau_dot: jax.Array
    stable: jax.Array


@dataclass(frozen=True, eq=False)  # hashed by content (fingerprint), a static jit argument
class Simulator:
    """A compiled tree model ready for batched rollouts. Build with :func:`make_simulator`.

    Attributes:
      mj_model: the MuJoCo C model (reference path, exports).
      model: the MJX model (device arrays; built on first use).
      joint_names: names of the inferred joints (order of the Kp/Kd columns).
      joint_ids, dof_ids: their MuJoCo joint and dof indices.
      grasp_body, grasp_site: indices of the grasped body and the grasp-point site.
      grasp_start, grasp_end: [3] the grasped branch's axis in its body frame
        (grasp fraction f puts C at ``start + f * (end - start)``).
      obs_dt: s between observations. substeps: simulation steps per observation.
      gravity_dir: [3] unit vector along gravity (the "downward" axis).
      backend: ``"fused"`` (MuJoCo's implicitfast step for hinge trees, fused into a few XLA
        kernels: :mod:`treeinfer.sim.fused`) or ``"mjx"`` (``mjx.step``).
      hinge_tree: the fused backend's static model (None for ``"mjx"``).
      grasp_fraction: the tree's grasp fraction (the default of :func:`simulate`'s
        ``grasp_fraction`` on other branches).
      force_interp: ``"linear"`` (first-order hold between force samples) or ``"hold"``
        (zero-order hold); see the module docstring for the exact convention.
      prior_box: (lower [2R], upper [2R]) the tree's prior box (``Tree.bounds_array``), used to
        pick the parameter sets of the accuracy check.
      branches: {branch name: (body index, length in m)} of every body the force may grasp.
      branch_axes: {body index: (start [3], end [3])} m, link axes of a user model in their
        body frames (absent: the axis runs along local x from 0 to the branch length).
      model_report: a user model's preparation report (:mod:`treeinfer.tree.usermodel`), else {}.
      step_layout: the fused step's layout: ``"scalar"``, ``"levels"`` or ``"auto"`` (by joint
        count; :mod:`treeinfer.sim.fused_backend`).
      step_info: how ``substeps`` was chosen: ``{"method": "given" | "stability" |
        "accuracy", "stability_substeps": int, "tolerance": m, "estimated_error": m}``.
    """

    mj_model: object
    joint_names: tuple[str, ...]
    joint_ids: np.ndarray
    dof_ids: np.ndarray
    grasp_body: int
    grasp_site: int
    grasp_start: np.ndarray
    grasp_end: np.ndarray
    obs_dt: float
    substeps: int
    gravity_dir: np.ndarray
    settle_iterations: int = 30
    max_displacement: float = 5.0
    max_joint_speed: float = 200.0
    settle_tolerance: float = 1e-3
    backend: str = "mjx"
    hinge_tree: object = None
    force_interp: str = "linear"
    grasp_fraction: float = 1.0
    prior_box: tuple = ()
    branches: dict = field(default_factory=dict)
    step_info: dict = field(default_factory=dict)
    branch_axes: dict = field(default_factory=dict)
    model_report: dict = field(default_factory=dict)
    step_layout: str = "auto"
    # what was derived from this simulator and is worth keeping while it lives (the force-noise
    # Jacobian and its compiled program: treeinfer.model.force_noise.force_jacobian). Held here,
    # not in a module, so it goes with the simulator its owner keeps (runs' SimulatorCache) and
    # a new simulator (dataclasses.replace) starts empty; not part of the fingerprint.
    derived: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @functools.cached_property
    def fingerprint(self) -> str:
        """sha256 of the compiled MuJoCo model (``mj_saveModel`` bytes) and every other field:
        equal fingerprints trace to the same program."""
        import mujoco

        h = hashlib.sha256()
        buf = np.zeros(mujoco.mj_sizeModel(self.mj_model), np.uint8)
        mujoco.mj_saveModel(self.mj_model, None, buf)
        h.update(buf.tobytes())
        for f in fields(self):
            if f.name in ("mj_model", "hinge_tree", "derived"):  # hinge_tree: read from mj_model
                continue
            h.update(f.name.encode())
            h.update(_canonical(getattr(self, f.name)).encode())
        return h.hexdigest()

    def program_key(self, traced_substeps: bool) -> str:
        """The simulator's part of a persistent program's key (``treeinfer.sim.startup``'s
        ``cached_program`` and ``stored_export``): its content without ``step_info`` (how its
        step was chosen: metadata that differs between data sets whose accuracy-controlled
        step came out the same). A program that takes the substep count as an argument
        (``traced_substeps``) never reads the step (``substeps`` and the model's timestep: the
        fused pull and the Pallas kernel divide ``obs_dt`` by the traced count), so its key
        leaves the step out too, and a data set whose accurate step differs loads the program
        traced for an earlier one instead of tracing the simulator again (about 1 s on a GPU,
        BENCHMARKS.md). MJX reads the model's timestep, so its key keeps it."""
        if not traced_substeps or self.backend == "mjx":
            return dataclasses.replace(self, step_info={}).fingerprint
        opt = self.mj_model.opt
        own = opt.timestep
        try:  # the fingerprint hashes the saved model: its timestep set to one canonical value
            opt.timestep = self.obs_dt
            return dataclasses.replace(self, step_info={}, substeps=1).fingerprint
        finally:
            opt.timestep = own

    def __hash__(self) -> int:
        return hash(self.fingerprint)

    def __eq__(self, other) -> bool:
        if self is other:
            return True
        return isinstance(other, Simulator) and self.fingerprint == other.fingerprint

    @functools.cached_property
    def model(self):
        # eager even when first touched inside a jit trace: the cached arrays must be concrete
        with jax.ensure_compile_time_eval():
            return _mjx_backend.put_model(self.mj_model)

    @property
    def dtype(self):
        """Float type of the rollout: float32, or float64 when ``jax_enable_x64`` is on (read
        from the config: ``jnp.asarray(0.0)`` would put an array on the device, the first of
        which pays the GPU client's start)."""
        return jnp.dtype(jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)

    @property
    def n_joints(self) -> int:
        return len(self.joint_ids)

    @property
    def sim_dt(self) -> float:
        return self.obs_dt / self.substeps

    def branch_point(self, body, length: float, fraction) -> jax.Array:
        """[..., 3] point at ``fraction`` [...] of a branch's axis, in its body's frame (``body``
        None: the grasped body)."""
        f = jnp.asarray(fraction, dtype=self.dtype)[..., None]
        bid = self.grasp_body if body is None else int(body)
        if bid in self.branch_axes:
            a, e = (jnp.asarray(x, self.dtype) for x in self.branch_axes[bid])
            return a + f * (e - a)
        return f * jnp.asarray([length, 0.0, 0.0], self.dtype)

    def grasp_point(self, fraction) -> jax.Array:
        """Grasp point in the grasped body's frame for a fraction of the branch length."""
        f = jnp.asarray(fraction, dtype=self.dtype)
        return jnp.asarray(self.grasp_start) + f[..., None] * jnp.asarray(
            self.grasp_end - self.grasp_start
        )


def _canonical(x) -> str:
    """A deterministic text form of a Simulator field (arrays by dtype, shape and bytes)."""
    if isinstance(x, np.ndarray):
        return f"nd{x.dtype}{x.shape}{x.tobytes().hex()}"
    if isinstance(x, dict):
        items = sorted(x.items(), key=repr)
        return "{" + ",".join(f"{k!r}:{_canonical(v)}" for k, v in items) + "}"
    if isinstance(x, (tuple, list)):
        return "(" + ",".join(_canonical(v) for v in x) + ")"
    if isinstance(x, float):
        return x.hex()
    return repr(x)
