"""Noise on the recorded force as an errors-in-variables term (``--noise-force``).

The simulator is driven by the RECORDED force ``F_rec = F_true + e``, ``e[b, s]`` i.i.d.
``Normal(0, sigma_F)`` per sample (one sensor: the same std on every sample and every pull).
The recorded displacement is ``x_rec = x_sim(theta, F_true) + n`` with white ``n ~ N(0, sigma_x)``.
Linearising the simulation in the force around the recorded one,

    x_sim(theta, F_true) ~ x_sim(theta, F_rec) - J e,      J = d x_sim / d F   [T, T] per pull,

so, marginalising the unknown ``e`` exactly (it is Gaussian and enters linearly),

    x_rec | theta ~ MVN(x_sim(theta, F_rec), C + sigma_x^2 I),    C = sigma_F^2 J J^T.

Why this and not the alternatives:

* treating the noise-free force as B x T latent variables (the textbook errors-in-variables
  model) costs two black-box simulations per latent per gradient: not feasible;
* absorbing it into an inflated i.i.d. sigma_x (what ``--likelihood gaussian`` did before)
  misses that the force-induced error is SLOW (the branch low-passes it: lag-1 autocorrelation
  0.95-0.99) and that its size varies along the pull; predictive bands then miss 7-10% of noisy
  test points instead of 5% (``experiments/README.md``, "Force noise");
* ``ar1`` models a stationary slow error, but the force-induced one is not stationary (it is
  zero at t = 0 and grows with the branch's response).

``J`` is the exact forward-mode Jacobian of the batched simulator in its force input
(``jax.jacfwd``; the simulator is causal, so ``J`` is lower triangular; with first-order-hold
force interpolation its diagonal is not zero; on the Pallas backend it is taken through the
fused twin, whose XLA step ``jacfwd`` differentiates in the force, and checked against a central
difference of the run's own simulator: :func:`force_jacobian`). It depends on theta mainly
through the branch's compliance; it is evaluated ONCE, at a reference parameter ``theta_ref``:
by default the MAP of this errors-in-variables model (:func:`reference_theta`:
Levenberg-Marquardt from several starts in the prior box,
:func:`treeinfer.inference.mapfit.fit_map`, first without the force term, then with it).
Why the MAP and not the prior median: the prior box spans one to two orders of magnitude in each
gain, and ``J`` scales with the compliance, so ``C`` at the prior median can be off by that
factor; the posterior is narrow (a few % in the identified gains), so ``J`` at the MAP is ``J``
at every posterior draw to a few %. With ``C = U diag(L) U^T`` (``numpy.linalg.eigh``, once per
pull, float64) the density for any sigma_x is exact and O(T^2) per particle: rotate the residual
by ``U^T`` and sum independent numpyro ``Normal(0, sqrt(L + sigma_x^2))`` log densities
(:func:`mvn_log_prob`); sigma_x stays a free (inferred) parameter.

The bias correction (the recorded force drives the simulator, so the fit prefers gains with
a small response to force noise): :mod:`treeinfer.model.force_noise_bias`, added by
:func:`mvn_log_prob` where the basis carries its slope.

Predictive bands of a recording driven by a noisy force carry the same term, built from that
recording's own force (:func:`force_noise_basis` on the test forces, at the same ``theta_ref``):
draws are ``x_sim + U sqrt(L + sigma_x^2) z`` (:func:`predictive_draws`), and point-wise bands
add ``diag C`` to each particle's ``sigma_x^2`` (:func:`point_variance`).

``--noise-force`` (N per sample, a percentage of the peak force, or ``"auto"``):
:mod:`treeinfer.model.force_noise_option`. Several references, one per lobe of the posterior:
:mod:`treeinfer.model.force_noise_local`.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import SimulationError
from .force_noise_option import (  # noqa: F401 -- the option's functions, re-exported here
    _force_range,
    check_noise_force,
    estimate_force_noise,
    resolve_noise_force,
)

__all__ = [
    "ForceNoiseBasis",
    "check_noise_force",
    "estimate_force_noise",
    "force_jacobian",
    "force_noise_basis",
    "force_noise_covariance",
    "mvn_log_prob",
    "point_variance",
    "predictive_draws",
    "resolve_noise_force",
]


# --------------------------------------------------------------------------- J, C, basis


def _force_differentiable(sim):
    """The simulator whose forward mode carries force tangents, for :func:`force_jacobian`.

    ``sim`` itself, except on the Pallas backend (``backend="pallas"``, what ``"auto"`` picks on
    a GPU): its ``custom_jvp`` (:mod:`treeinfer.sim.pallas`) pushes tangents of (kp, kd) only
    and returns a ZERO tangent for the forces, silently, so ``jax.jacfwd`` in the force gave
    ``J = 0`` there and the errors-in-variables term vanished on the GPU (issue 11: the full-size
    coverage runs). Its fused twin runs the same step arithmetic (the kernel IS
    :func:`treeinfer.sim.fused.step`, agreeing to float32 rounding: ``tests/test_pallas_backend``)
    in plain XLA, which ``jacfwd`` differentiates in every input."""
    if sim.backend == "pallas":
        return dataclasses.replace(sim, backend="fused")
    return sim


# Directional check of J against the simulator's own primal rollouts (see force_jacobian):
# perturbation per sample as a share of the largest |force|, and the allowed relative error.
_CHECK_STEP = 0.01
_CHECK_RTOL = 0.02
# J of the last few (theta, forces) of a simulator, kept on it (Simulator.derived): a run's
# likelihood, training band and fit verdict take J at one reference (5-10 s each on 2 cores)
_KEPT_SIZE = 8  # the references of a run's lobes (force_noise_local) among them
_KEPT_MAX_BYTES = 64 * 2**20  # a J larger than this (long or many pulls) is not kept


def force_jacobian(
    sim,
    theta,
    forces,
    grasp_fraction=None,
    check: bool = True,
    substeps: int | None = None,
    keep: bool = True,
) -> np.ndarray:
    """``J[b] = d tau[b, :] / d forces[b, :]`` at ``theta [2R]``: ``[B, T, T]`` (m/N, float64).

    Exact forward mode (``jax.jacfwd``) through :func:`treeinfer.sim.simulate`, one pull at a
    time under ``vmap``; ``J[b, t, s]`` is the change of the displacement at sample t per newton
    at force sample s. On the Pallas backend the Jacobian is taken through the fused twin of
    ``sim`` (:func:`_force_differentiable`: the kernel's JVP drops force tangents).
    ``substeps``: the step J is taken at (default the simulator's own); it is an argument of one
    compiled program, so every step, reference and pull set of a shape shares it. (Why not the
    merely stable step, an eighth of the cost: J there is 0.9% (Frobenius) from the accurate J on
    the standard problem but up to 11% off in single columns, the response to a force at the
    first samples, against MuJoCo C in ``tests/test_force_noise_backends.py``.)

    ``check`` (default on): one directional central difference of ``sim``'s OWN rollouts
    (``tau(F + h v) - tau(F - h v)``, ``v`` random signs, ``h`` 1% of the largest |force|, one
    batched call of 2B pulls, at ``sim``'s own step) must match ``2 h J v`` to 2% (norm over
    each pull, plus a float rounding floor); else :class:`SimulationError`. It guards against a
    backend whose derivative in the force is wrong or missing (a zero ``J`` is not an error
    anywhere else: the term would silently vanish). Raises :class:`SimulationError` too if the
    rollout at ``theta`` is unstable.

    The result of the last few calls is kept on the simulator (``sim.derived``, keyed by its
    content, ``theta``, the forces and the grasp points), so a run's likelihood, training fit
    and fit verdict, which share the run's simulator, take J once."""
    from .gains import gains_from_theta

    dtype = sim.dtype
    theta64 = np.asarray(theta, float).reshape(-1)
    forces64 = np.atleast_2d(np.asarray(forces, float))
    gf64 = (
        None
        if grasp_fraction is None
        else np.broadcast_to(np.asarray(grasp_fraction, float), forces64.shape[:1])
    )
    jsim = _force_differentiable(sim)
    key = (
        sim.fingerprint,
        jsim.fingerprint,
        theta64.tobytes(),
        forces64.shape,
        forces64.tobytes(),
        None if gf64 is None else gf64.tobytes(),
        bool(check),
        substeps,
    )
    kept = sim.derived.setdefault("force_jacobians", collections.OrderedDict())
    if key in kept:
        kept.move_to_end(key)
        return kept[key].copy()
    th = jnp.asarray(theta64[None], dtype)
    kp, kd = gains_from_theta(th, sim.n_joints)
    f = jnp.asarray(forces64, dtype)
    gf = None if gf64 is None else jnp.asarray(gf64, dtype)
    n_b, n_t = forces64.shape
    v = np.random.default_rng(0).choice([-1.0, 1.0], size=(n_b, n_t))
    h = _CHECK_STEP * max(float(np.max(np.abs(forces64))), 1e-12)
    # the check's rollouts in the same program (one compilation), except on the Pallas backend,
    # whose own kernel is what the check must run
    fused_check = check and jsim is sim
    step = int(sim.substeps) if substeps is None else int(substeps)
    args = (kp, kd, f, jnp.asarray(h * v, dtype), np.int32(step), np.int32(sim.substeps))
    args += () if gf is None else (gf,)
    jac, ok, tau_pm, ok_pm = _jacobian_runner(jsim, fused_check, args)(*args)
    jac = np.asarray(jac, float)
    if not (np.all(np.asarray(ok)) and np.all(np.isfinite(jac))):
        raise SimulationError(
            "force noise: the simulation at the reference parameters is unstable on some "
            "pull; give another reference (force_noise_reference)"
        )
    if check:
        if fused_check:
            tau_pm, ok_pm = np.asarray(tau_pm, float), np.asarray(ok_pm)
        else:
            tau_pm, ok_pm = _check_rollouts(sim, kp, kd, forces64, gf, h * v)
        _raise_bad(_check_failures(forces64, tau_pm, ok_pm, h, v, jac, dtype), sim.backend)
    if keep and jac.nbytes <= _KEPT_MAX_BYTES:  # the bias slope's 2R Jacobians are not kept
        kept[key] = jac.copy()
        while len(kept) > _KEPT_SIZE:
            kept.popitem(last=False)
    return jac


def _jacobian_runner(jsim, with_check: bool, args):
    """:func:`_jacobian_program` of ``jsim`` as a function of ``args`` ``(kp, kd, forces, hv,
    substeps, check_substeps[, gf])`` (the grasp points last, where given), traced once per
    machine (:func:`treeinfer.sim.startup.cached_program`: a new process deserializes the stored
    program instead of tracing the simulator's forward mode again, 3-6 s on a 2-core CPU) and
    kept on ``jsim`` (``Simulator.derived``) while it lives."""
    from ..sim.startup import cached_program

    shapes = tuple((tuple(np.shape(a)), str(jnp.result_type(a))) for a in args)
    key = repr(("force_noise._jacobian_program", jsim.program_key(True), with_check, shapes))
    runners = jsim.derived.setdefault("force_jacobian_programs", {})
    run = runners.get(key)
    if run is None:

        def fn(kp, kd, forces, hv, substeps, check_substeps, *gf):
            g = gf[0] if gf else None
            return _jacobian_program(
                jsim, kp, kd, forces, g, hv, substeps, check_substeps, with_check
            )

        run = runners[key] = cached_program(fn, args, key)
    return run


def _jacobian_program(jsim, kp, kd, forces, gf, hv, substeps, check_substeps, with_check):
    """:func:`force_jacobian`'s program with the gains, the step (``substeps``, traced) and the
    perturbation ``hv [B, T]`` as arguments (a closure over the gains compiled anew at every
    reference point: 10-30 s each on a 2-core CPU). With ``with_check`` it also returns the
    rollouts ``tau(F + hv)``, ``tau(F - hv)`` at ``check_substeps`` (``[2B, T]``) and their
    stability, else zeros."""
    from ..sim import _simulate, _simulate_force_jacobian, simulate

    def run(kp, kd, f, g, s):
        if jsim.backend == "pallas":  # the kernel's own step (only where a test asks for it)
            return simulate(jsim, kp, kd, f, g)
        return _simulate(jsim, kp, kd, f, g, substeps=s)

    def one(f, g):
        def tau(fb):
            ro = run(kp, kd, fb[None], None if g is None else g[None], substeps)
            return ro.tau[0, 0], ro.stable[0, 0]

        return jax.jacfwd(tau, has_aux=True)(f)

    fast = None
    if jsim.backend != "pallas":  # the force tangents as one axis, not a vmap level
        fast = _simulate_force_jacobian(jsim, kp[0], kd[0], forces, gf, substeps)
    if fast is not None:
        _, ok, jac = fast
    elif gf is None:
        jac, ok = jax.vmap(lambda f: one(f, None))(forces)
    else:
        jac, ok = jax.vmap(one)(forces, gf)
    both = jnp.concatenate([forces + hv, forces - hv])
    if not with_check:
        return jac, ok, jnp.zeros(both.shape, forces.dtype), jnp.ones(both.shape[:1], bool)
    g2 = None if gf is None else jnp.concatenate([gf, gf])
    ro = run(kp, kd, both, g2, check_substeps)
    return jac, ok, ro.tau[0], ro.stable[0]


def _check_rollouts(sim, kp, kd, forces, gf, hv):
    """``(tau [2B, T], stable [2B])`` of ``sim``'s own rollouts of ``forces +- hv``."""
    from ..sim import simulate

    both = np.concatenate([forces + hv, forces - hv])
    g2 = None if gf is None else jnp.concatenate([gf, gf])
    ro = simulate(sim, kp, kd, jnp.asarray(both, sim.dtype), g2)
    return np.asarray(ro.tau[0], float), np.asarray(ro.stable[0])


def _check_failures(forces, tau, stable, h, v, jac, dtype):
    """None when ``jac [B, T, T]`` predicts the central difference of the rollouts ``tau
    [2B, T]`` of ``forces +- h v`` to :data:`_CHECK_RTOL` (or a perturbed pull blew up: nothing
    to compare), else ``(pull, relative error)`` of the worst pull."""
    n_b, n_t = forces.shape
    if not np.all(stable):
        return None  # a perturbed pull blew up: nothing to compare (the unperturbed one is stable)
    fd = tau[:n_b] - tau[n_b:]  # [B, T] m
    lin = 2.0 * h * np.einsum("bts,bs->bt", jac, v)
    # float rounding of the two rollouts: a few ulps of the displacement's scale
    eps = float(np.finfo(np.dtype(dtype)).eps)
    floor = 10.0 * eps * np.abs(tau[:n_b]).max(axis=1) * math.sqrt(n_t)
    err = np.linalg.norm(fd - lin, axis=1)
    bad = err > _CHECK_RTOL * np.linalg.norm(fd, axis=1) + floor
    if not np.any(bad):
        return None
    b = int(np.argmax(bad))
    return b, err[b] / max(float(np.linalg.norm(fd[b])), 1e-300)


def _check_force_jacobian(sim, kp, kd, forces, gf, jac) -> None:
    """Raise :class:`SimulationError` unless ``jac [B, T, T]`` predicts ``sim``'s own response
    to a small random force perturbation (see :func:`force_jacobian`)."""
    n_b, n_t = forces.shape
    v = np.random.default_rng(0).choice([-1.0, 1.0], size=(n_b, n_t))
    h = _CHECK_STEP * max(float(np.max(np.abs(forces))), 1e-12)
    tau, ok = _check_rollouts(sim, kp, kd, forces, gf, h * v)
    _raise_bad(_check_failures(forces, tau, ok, h, v, jac, sim.dtype), sim.backend)


def _raise_bad(bad, backend) -> None:
    """:class:`SimulationError` for a failed check ``bad = (pull, relative error)``."""
    if bad is not None:
        b, rel = bad
        raise SimulationError(
            f"force noise: the forward-mode force Jacobian (backend {backend!r}) does not "
            f"match a central difference of the simulator on pull {b} (relative error "
            f"{rel:.2g}); the backend's derivative in the force is wrong or missing"
        )


def force_noise_covariance(jac, sigma_force: float, mask=None) -> np.ndarray:
    """``C[b] = sigma_F^2 J[b] diag(m[b]) J[b]^T``, masked to real samples: ``[B, T, T]`` (m^2).

    ``jac``: ``[B, T, T]`` from :func:`force_jacobian`; ``mask`` ``[B, T]`` bool (None: all real).
    Rows and columns of padded samples are zero (force noise exists only on real samples)."""
    jac = np.asarray(jac, float)
    m = np.ones(jac.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    jm = jac * m[:, :, None] * m[:, None, :]
    return float(sigma_force) ** 2 * np.einsum("bts,bus->btu", jm, jm)


class ForceNoiseBasis(NamedTuple):
    """Eigen-decomposition of the force-induced covariance of each pull.

    vectors: ``[B, T, T]`` U (columns are eigenvectors), values: ``[B, T]`` L >= 0 (m^2), so
    ``C[b] = U[b] diag(L[b]) U[b]^T``. n_pad: ``[B]`` padded samples per pull (their rows and
    columns of C are zero; :func:`mvn_log_prob` takes their white-noise terms out again).
    """

    vectors: np.ndarray
    values: np.ndarray
    n_pad: np.ndarray
    slope: np.ndarray | None = None  # [B, T, 2R] d(u_i^T C u_i)/d theta (m^2), with_bias_slope
    theta_ref: np.ndarray | None = None  # [2R] where C and the slope were taken

    def covariance(self) -> np.ndarray:
        """``C [B, T, T]`` back from the basis (m^2; stacked: its first reference's)."""
        from .force_noise_local import primary

        u, lam = primary(self).vectors, primary(self).values
        return np.einsum("bts,bs,bus->btu", u, lam, u)


def force_noise_basis(
    sim, theta_ref, forces, sigma_force: float, mask=None, grasp_fraction=None
) -> ForceNoiseBasis:
    """:class:`ForceNoiseBasis` of ``C = sigma_F^2 J J^T`` for the pulls ``forces [B, T]`` (N) at
    ``theta_ref [2R]`` (``numpy.linalg.eigh`` in float64, once per pull)."""
    forces = np.atleast_2d(np.asarray(forces, float))
    m = np.ones(forces.shape, bool) if mask is None else np.asarray(mask, bool)
    # kept on the simulator as J is: a run builds the same basis for its reference problem,
    # its final problem, the training fit's band and the fit verdict (an eigh of each pull's
    # [T, T] covariance every time)
    key = _basis_key(sim, "basis", theta_ref, forces, sigma_force, m, grasp_fraction)
    kept = sim.derived.setdefault("force_noise_bases", collections.OrderedDict())
    if key in kept:
        kept.move_to_end(key)
        return ForceNoiseBasis(*(None if x is None else np.array(x) for x in kept[key]))
    cov = force_noise_covariance(
        force_jacobian(sim, theta_ref, forces, grasp_fraction), sigma_force, m
    )
    lam, u = np.linalg.eigh(cov)
    basis = ForceNoiseBasis(u, np.clip(lam, 0.0, None), (~m).sum(axis=1))
    if u.nbytes <= _KEPT_MAX_BYTES:
        kept[key] = ForceNoiseBasis(*(None if x is None else np.array(x) for x in basis))
        while len(kept) > _KEPT_SIZE:
            kept.popitem(last=False)
    return basis


def _basis_key(sim, what, theta, forces, sigma_force, mask, grasp_fraction, *more):
    """The key of a basis (or its bias slope) kept on ``sim.derived``: the simulator's content
    and every input, as bytes."""
    gf = None if grasp_fraction is None else np.asarray(grasp_fraction, float).tobytes()
    theta = np.asarray(theta, float).reshape(-1).tobytes()
    return (what, sim.fingerprint, theta, forces.shape, forces.tobytes(), float(sigma_force),
            np.asarray(mask, bool).tobytes(), gf, *more)  # fmt: skip


def mvn_log_prob(residual, basis: ForceNoiseBasis, sigma_x, theta_gains=None) -> jax.Array:
    """``sum_b log MVN(residual[n, b] | 0, C[b] + sigma_x[n]^2 I)`` over real samples: ``[N]``,
    plus the bias correction (module docstring) when ``basis`` has a slope and ``theta_gains``
    is given.

    Args:
      residual: ``[N, B, T]`` m, recorded minus simulated displacement, ZERO at padded samples.
      basis: from :func:`force_noise_basis` for the same pulls (:func:`with_bias_slope`: with
        the correction's slope).
      sigma_x: ``[N]`` m, white displacement noise per row.
      theta_gains: ``[N, 2R]`` the rows' log gains (None: no correction).

    In the eigenbasis the MVN factorises into independent normals ``z = U^T r``,
    ``z_i ~ Normal(0, sqrt(L_i + sigma_x^2))`` (numpyro); O(B T^2) per row. Padded samples
    contribute ``log N(0; 0, sigma_x)`` each to that full density (C is zero there) and are
    taken out again, so the result is the exact density of the real samples."""
    import numpyro.distributions as dist  # here, not at the top: keeps it off the start-up path

    from .force_noise_local import is_stacked, reference_weights, split

    if is_stacked(basis):  # one reference per lobe of the posterior (force_noise_local)
        parts = split(basis)
        if theta_gains is None:
            return mvn_log_prob(residual, parts[0], sigma_x)
        each = [mvn_log_prob(residual, b, sigma_x, theta_gains) for b in parts]
        w = reference_weights(theta_gains, basis.theta_ref)
        # a reference whose density is -inf where its weight underflows to 0 gives no NaN
        return jnp.sum(jnp.where(w > 0, w * jnp.stack(each, axis=-1), 0.0), axis=-1)
    r = jnp.asarray(residual)
    u = jnp.asarray(basis.vectors, r.dtype)
    lam = jnp.asarray(basis.values, r.dtype)
    sx = jnp.asarray(sigma_x, r.dtype)
    z = jnp.einsum("bts,nbt->nbs", u, r)
    var = lam[None] + sx[:, None, None] ** 2
    total = jnp.sum(dist.Normal(0.0, jnp.sqrt(var)).log_prob(z), axis=(-2, -1))
    n_pad = jnp.asarray(np.sum(basis.n_pad), r.dtype)
    total = total - n_pad * dist.Normal(0.0, sx).log_prob(jnp.zeros_like(sx))
    if basis.slope is not None and theta_gains is not None:
        # the standardised correction (force_noise_bias docstring): each direction's residual
        # is weighed by the force-induced variance at THIS theta, d_i(theta) = u_i^T C(theta)
        # u_i to first order (floored at 0: C is positive semi-definite), the normalisation kept
        # at the reference
        dth = bias_offset(jnp.asarray(theta_gains, r.dtype) - jnp.asarray(basis.theta_ref, r.dtype))
        delta = jnp.einsum("bsj,nj->nbs", jnp.asarray(basis.slope, r.dtype), dth)
        var_theta = jnp.maximum(lam[None] + delta, 0.0) + sx[:, None, None] ** 2
        total = total + 0.5 * jnp.sum(z**2 * (1.0 / var - 1.0 / var_theta), axis=(-2, -1))
    return total


BIAS_STEP = 0.01  # log-gain step of the bias slope's forward differences
# log gains from the reference beyond which the first-order correction is held constant: its
# linear extrapolation is unbounded (a weakly identified damping 3 log units below the
# reference gained 30 nats on chain2, and the fit ran there) while the trace it stands for
# saturates; the start pipeline takes the correction again at a MAP that moved
# (treeinfer.inference.start_pipeline.force_noise_reference)
BIAS_TRUST = 0.5


def bias_offset(dth):
    """``dth`` (log gains from the correction's reference), saturated smoothly at
    ``BIAS_TRUST``: ``c tanh(dth / c)`` (exact to third order near the reference)."""
    return BIAS_TRUST * jnp.tanh(dth / BIAS_TRUST)


def point_variance(basis: ForceNoiseBasis) -> np.ndarray:
    """``diag C`` per pull and sample: ``[B, T]`` (m^2), the force-induced variance each point of
    a point-wise predictive band adds to ``sigma_x^2`` (a stacked basis: its first reference's)."""
    from .force_noise_local import primary

    basis = primary(basis)
    return np.einsum("bts,bs->bt", basis.vectors**2, basis.values)


def predictive_draws(key, pred, sigma_x, basis: ForceNoiseBasis) -> jax.Array:
    """Posterior-predictive draws of recordings driven by a noisy force: ``[P, B, T]`` (m).

    ``pred [P, B, T]`` simulations, ``sigma_x [P]`` m; draw p is
    ``pred[p] + U diag(sqrt(L + sigma_x[p]^2)) z``, z standard normal (one draw per particle)."""
    from .force_noise_local import primary

    pred, basis = jnp.asarray(pred), primary(basis)
    u = jnp.asarray(basis.vectors, pred.dtype)
    lam = jnp.asarray(basis.values, pred.dtype)
    sx = jnp.broadcast_to(jnp.asarray(sigma_x, pred.dtype), pred.shape[:1])
    z = jax.random.normal(key, pred.shape, pred.dtype)
    scaled = z * jnp.sqrt(lam[None] + sx[:, None, None] ** 2)
    return pred + jnp.einsum("bts,pbs->pbt", u, scaled)
