"""The fused hinge-tree step as ONE GPU kernel per block of rollouts (``backend="pallas"``).

Why: on a GPU the fused backend (:mod:`treeinfer.sim.fused`) runs each simulation step as ~2
XLA kernels inside a ``while`` loop; the standard problem needs 300 observations x 4 substeps =
1200 *sequential* steps per rollout, so an NNSVGD iteration is bound by kernel launches and
loop overhead (~15 us per step on an H100), not by arithmetic. XLA's loop levers (command
buffers with WHILE, unrolling, while-loop double buffering) were measured in
``BENCHMARKS.md``: none comes near the 5 ms target. Here one Pallas kernel (Triton on the GPU)
loops over every observation and substep itself; each lane of a [BLOCK] vector is one
(parameter set, force profile) rollout whose state stays in registers, the force profile is read
one sample per observation and ``tau`` written one sample per observation.

The arithmetic is :func:`treeinfer.sim.fused.step` itself, unchanged: its element functions
work on [BLOCK] arrays as they work on scalars (only ``+ - * /``, ``sin``, ``cos``, ``where``).
The settle (static Newton solve) and the observation bookkeeping are shared with the fused
backend, so the two agree to float32 rounding (``tests/test_pallas_backend.py``, interpret mode
on the CPU). Profiles grouped by grasp branch or a traced ``substeps`` (the accuracy check) are
handed to the fused path unchanged.

Exact forward-mode tangents: :func:`simulate_with_tangents` carries K tangent directions of
(kp, kd) through the same kernel, in one of three layouts (:data:`TANGENT_LAYOUTS`): ``"rows"``
and ``"lanes"`` push each tangent through ``jax.linearize`` of the whole step (the linearised
kinematics, bias forces, mass matrix and LDL once per tangent); ``"sensitivity"`` computes the
step's state Jacobian once per substep from the primal (:mod:`treeinfer.sim.sensitivity`, the
fused backend's rule on the CPU) and applies it to each tangent with ~100 multiply-adds.

This module is the dispatch: when the kernel runs (:func:`supported`, :func:`resolve`), its
switches (read here at call time, so tests and benchmarks set them here), :func:`simulate` and
its exact JVP. The kernel itself is :mod:`treeinfer.sim.pallas_kernel`, the packing of rollouts
into the kernel's rows :mod:`treeinfer.sim.pallas_layout` (issue 26); both are re-exported here.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .pallas_kernel import (  # noqa: F401 -- re-exported: they lived here before the split
    INTERPRET_WHOLE_BATCH,
    _rollout_kernel,
    _rollout_rows,
    _sensitivity_substep,
    _use_interpret,
)
from .pallas_layout import _finish, _pad, _prepare, _rows  # noqa: F401 -- re-exported

DEFAULT_BLOCK = 32  # rollouts per kernel instance (one warp): spreads small batches over SMs


# The substep count as a runtime operand of the (value-only) kernel, a loop bound, instead of a
# constant: one compiled kernel then serves every accurate step, so a new data set whose step
# differs, the multi-fidelity fit's coarse step and the step check (issue 15 item 4) reuse it.
# On by default since it was timed on an H100 (BENCHMARKS.md, "H100: a cold process on a NEW
# data set"): a new recording of the bucket then compiles nothing (3.9 s to a posterior, against
# 7.2-8.6 s with one kernel compile per new step), and an empty cache compiles 6.8 s instead of
# 8.3 s; checked in the interpreter against the fused backend
# (tests/test_pallas_traced_substeps.py). Gradients (simulate_with_tangents) keep the constant
# count. Environment switch for timing it: TREEINFER_PALLAS_TRACED_SUBSTEPS=on|off (read once).
def _switch(name: str) -> bool:
    import os

    from ..errors import ConfigError

    value = os.environ.get(name, "on").strip().lower()
    if value not in ("on", "off", "1", "0"):
        raise ConfigError(f"{name}: expected on or off, got {value!r}")
    return value in ("on", "1")


TRACED_SUBSTEPS = _switch("TREEINFER_PALLAS_TRACED_SUBSTEPS")


# How simulate_with_tangents (and so the kernel's exact JVP) lays its K tangents out:
# * "rows": one tangent per lane beside its own copy of the primal, the step linearised with
#   jax.linearize (K copies of the primal plus K linearised steps: ~12-15 rollouts of arithmetic
#   for K = 6; a kernel as small as the primal's plus one; 1.0x central differences on an H100);
# * "lanes": one primal and all K tangents per lane, each tangent the whole linearised step
#   (~10 rollouts of arithmetic for K = 6; Triton took 182 s to compile it on an H100);
# * "sensitivity": one primal and all K tangents per lane, the step's state Jacobian computed
#   ONCE per substep from the primal (sensitivity.step_linearization) and applied to each
#   tangent (sensitivity.step_tangent: ~100 multiply-adds and a back-substitution), the rule
#   that brought the fused backend on the CPU to 0.20-0.24x of central differences.
# Timed on an H100 (BENCHMARKS.md, "exact gradients at half the cost of central differences"):
# once the GPU is full "sensitivity" takes 0.50x the wall time of central differences at
# P = 65536 (46.7 against 94.0 ms; 0.66x at 16384, where "rows" is 1.02-1.09x), but Triton
# compiles it in 90-98 s per batch shape, and at the standard problem's P = 128, where the
# rollouts are latency-bound and central differences cost one rollout's time, it is 3.5x slower
# than central differences ("rows": 1.7x). So "rows" stays the default; a long run at a large
# batch with a warm persistent cache sets TREEINFER_PALLAS_TANGENT_LAYOUT=sensitivity
# (rows|lanes|sensitivity, read once at import).
TANGENT_LAYOUTS = ("rows", "lanes", "sensitivity")


def _tangent_layout(name: str = "TREEINFER_PALLAS_TANGENT_LAYOUT", default: str = "rows") -> str:
    """The tangent layout named by environment variable ``name`` (unset or empty: ``default``);
    a ConfigError names the variable and the accepted values otherwise."""
    import os

    from ..errors import ConfigError

    value = os.environ.get(name, "").strip().lower() or default
    if value not in TANGENT_LAYOUTS:
        raise ConfigError(f"{name}: expected one of {', '.join(TANGENT_LAYOUTS)}, got {value!r}")
    return value


TANGENT_LAYOUT = _tangent_layout()


def available() -> bool:
    """Whether the Pallas Triton lowering can run here (a CUDA GPU and jax's Pallas).

    Looked up, not imported: importing Pallas and its Triton lowering costs 0.2-0.5 s of a cold
    process (issue 15), and a run whose programs come from the persistent caches never traces
    the kernel; the kernel's builder imports them when it does."""
    import importlib.util

    if jax.devices()[0].platform != "gpu":
        return False
    try:
        return importlib.util.find_spec("jax.experimental.pallas") is not None
    except (ImportError, ValueError):  # pragma: no cover - depends on the jax build
        return False


# ``backend="auto"`` picks the kernel on a GPU (measured faster there: ``BENCHMARKS.md``); on a
# CPU the interpreter is far slower than the fused XLA loop, so "auto" stays "fused".
AUTO_ON_GPU = True


def resolve(backend: str) -> str:
    """The backend a hinge-tree model runs on for the requested ``backend``: ``"pallas"`` when
    asked for, or for ``"auto"`` on a GPU with Pallas; ``"fused"`` otherwise."""
    if backend == "pallas" or (backend == "auto" and AUTO_ON_GPU and available()):
        return "pallas"
    return "fused"


def supported(sim, grasp_branch=None, substeps=None) -> bool:
    """Whether :func:`simulate` runs the kernel for this call (else the fused path does)."""
    from .fused_backend import uses_levels

    # the kernel runs the scalar (unrolled) fused step; big trees take the level layout
    return (
        sim.hinge_tree is not None
        and grasp_branch is None
        and (substeps is None or TRACED_SUBSTEPS)
        and not uses_levels(sim)
    )


def simulate(
    sim,
    kp,
    kd,
    forces,
    grasp_fraction=None,
    direction=None,
    block: int | None = None,
    interpret=None,
    substeps=None,
):
    """:func:`treeinfer.sim.simulate` through the whole-rollout kernel (same arguments and
    :class:`~treeinfer.sim.Rollout`; the grasp branch is the simulator's own). Differentiable
    in ``kp``/``kd`` (``jax.jvp``, ``jax.grad``): exact, from the kernel's tangents.

    ``substeps``: None (the simulator's own, a constant of the kernel), or a traced integer
    passed to the kernel as an operand (:data:`TRACED_SUBSTEPS`; values only, not
    differentiable).

    ``block``: rollouts per kernel instance (a power of two, >= 32 on the GPU; default
    ``DEFAULT_BLOCK``); ``interpret``: None (Triton on a GPU, Pallas's interpreter elsewhere),
    True or False."""
    block = DEFAULT_BLOCK if block is None else int(block)
    if substeps is not None:
        rows, _, settled, shape = _prepare(sim, kp, kd, forces, grasp_fraction, direction)
        tau, ok, _ = _rollout_rows(
            sim, rows["kp"], rows["kd"], rows["q_rest"], rows["site"], rows["dirs"], rows["f"],
            rows["fn"], None, None, None, substeps, block=block, interpret=interpret,
        )  # fmt: skip
        return _finish(sim, tau, ok, settled, shape)
    return _simulate_jvp(sim, block, interpret, kp, kd, forces, grasp_fraction, direction)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def _simulate_jvp(sim, block, interpret, kp, kd, forces, grasp_fraction, direction):
    rows, _, settled, shape = _prepare(sim, kp, kd, forces, grasp_fraction, direction)
    tau, ok, _ = _rollout_rows(
        sim, rows["kp"], rows["kd"], rows["q_rest"], rows["site"], rows["dirs"], rows["f"],
        rows["fn"], None, None, None, block=block, interpret=interpret,
    )  # fmt: skip
    return _finish(sim, tau, ok, settled, shape)


@_simulate_jvp.defjvp
def _simulate_jvp_rule(sim, block, interpret, primals, tangents):
    """Exact JVP in (kp, kd): the kernel pushes the 2R basis tangents (the Jacobian of the
    rollout, which does not depend on the incoming tangents, so ``vmap`` over tangent
    directions computes it once), and the output tangent is its product with the incoming
    tangent: linear and transposable, so reverse mode (``jax.grad``) works too. Tangents of the
    forces, grasp fraction and direction are not propagated (data, not parameters)."""
    kp, kd, forces, grasp_fraction, direction = primals
    kp, kd = jnp.atleast_2d(kp), jnp.atleast_2d(kd)
    dtheta = jnp.concatenate(
        [
            jnp.broadcast_to(_instantiate(tangents[0], kp), kp.shape),
            jnp.broadcast_to(_instantiate(tangents[1], kd), kd.shape),
        ],
        axis=-1,
    ).astype(sim.dtype)
    n_particles, r = kp.shape
    eye = jnp.eye(2 * r, dtype=sim.dtype)
    basis = jnp.broadcast_to(eye[:, None, :], (2 * r, n_particles, 2 * r))
    ro, jac = simulate_with_tangents(
        sim, kp, kd, forces, basis[..., :r], basis[..., r:], grasp_fraction, direction,
        block, interpret,
    )  # fmt: skip
    push = lambda j: jnp.einsum("kpbt,pk->pbt", j, dtheta)
    return ro, type(ro)(tau=push(jac.tau), tau_dot=push(jac.tau_dot), stable=_float0(ro.stable))


def _instantiate(x, like):
    if isinstance(x, jax.custom_derivatives.SymbolicZero) or x is None:
        return jnp.zeros_like(like)
    return x


def _float0(x):
    return np.zeros(np.shape(x), dtype=jax.dtypes.float0)


def simulate_with_tangents(
    sim,
    kp,
    kd,
    forces,
    dkp,
    dkd,
    grasp_fraction=None,
    direction=None,
    block: int | None = None,
    interpret=None,
    layout: str | None = None,
):
    """Rollout and K exact tangent rollouts in one kernel.

    Args: as :func:`simulate`; ``dkp``, ``dkd`` [K, P, R]: K tangent directions of the gains.
    Returns ``(Rollout, Rollout of tangents)`` with tangent ``tau``/``tau_dot`` [K, P, B, T]
    (``stable`` of the second is the first's). The settled rest pose's tangent comes from
    ``jax.jvp`` through the settle (a few Newton steps, XLA).

    ``layout`` (default :data:`TANGENT_LAYOUT`): ``"lanes"`` carries all K tangents in each lane
    beside one primal, each the whole linearised step (a large kernel, slow to compile),
    ``"rows"`` gives each tangent its own lanes with a copy of the primal (2K rollouts of
    arithmetic, but K times the parallelism for the GPU and a kernel as small as the primal's
    plus one), ``"sensitivity"`` carries all K tangents in each lane like ``"lanes"`` but
    linearises the step once per substep and applies that to each tangent (least
    arithmetic: the fused backend's rule)."""
    from .fused_backend import _prepare as _fused_prepare

    block = DEFAULT_BLOCK if block is None else int(block)
    dtype = sim.dtype
    kp, kd = jnp.atleast_2d(kp).astype(dtype), jnp.atleast_2d(kd).astype(dtype)
    dkp, dkd = jnp.asarray(dkp, dtype), jnp.asarray(dkd, dtype)
    n_tan = dkp.shape[0]
    rows, q_rest, settled, shape = _prepare(sim, kp, kd, forces, grasp_fraction, direction)
    n_particles, n_profiles, n_steps = shape

    def rest_q(a, b):
        return _fused_prepare(sim, a, b, dtype)[1]

    dq = jax.vmap(lambda ta, tb: jax.jvp(jax.vmap(rest_q), (kp, kd), (ta, tb))[1])(dkp, dkd)
    # [K, P, X] -> [K * X, P * B] rows (tangent a, component i at row a * X + i)
    layout = TANGENT_LAYOUT if layout is None else layout
    if layout in ("lanes", "sensitivity"):
        # [K, P, X] -> [K * X, P * B]: tangent a, component i at row a * X + i of every lane
        lay = lambda x: jnp.concatenate([_rows(x[a], n_profiles) for a in range(n_tan)], axis=0)
        rule = "linearize" if layout == "lanes" else "sensitivity"
        tau, ok, dtau = _rollout_rows(
            sim, rows["kp"], rows["kd"], rows["q_rest"], rows["site"], rows["dirs"], rows["f"],
            rows["fn"], lay(dkp), lay(dkd), lay(dq), block=block, interpret=interpret,
            rule=rule,
        )  # fmt: skip
    elif layout == "rows":
        # one tangent per lane: the lanes of tangent a are columns [a * N, (a + 1) * N)
        n = n_particles * n_profiles
        rep = {k: None if v is None else jnp.tile(v, (1, n_tan)) for k, v in rows.items()}
        lay = lambda x: jnp.concatenate([_rows(x[a], n_profiles) for a in range(n_tan)], axis=1)
        tau, ok, dtau = _rollout_rows(
            sim, rep["kp"], rep["kd"], rep["q_rest"], rep["site"], rep["dirs"], rep["f"],
            rep["fn"], lay(dkp), lay(dkd), lay(dq), block=block, interpret=interpret,
        )  # fmt: skip
        tau, ok = tau[:, :n], ok[:n]
        dtau = dtau.reshape(n_steps, n_tan, n).transpose(1, 0, 2).reshape(n_tan * n_steps, n)
    else:
        raise ValueError(f"layout: one of {', '.join(TANGENT_LAYOUTS)}, got {layout!r}")
    ro = _finish(sim, tau, ok, settled, shape)
    from . import velocity

    dtau = dtau.reshape(n_tan, n_steps, n_particles, n_profiles).transpose(0, 2, 3, 1)
    mask = ro.stable[None, ..., None]
    dtau = jnp.where(mask, dtau, 0.0)
    dtau_dot = jnp.where(mask, velocity(dtau, sim.obs_dt), 0.0)
    return ro, type(ro)(tau=dtau, tau_dot=dtau_dot, stable=ro.stable)
