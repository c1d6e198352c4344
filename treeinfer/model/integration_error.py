"""The simulator's discretisation error as a known part of the residual (issue 27, clean data).

Why: treeinfer's simulator (MuJoCo's first-order ``implicitfast`` step, ``substeps`` per
observation) is off an exact integration of the same equations by a small, smooth error
``e(t; theta)``. On a noisy recording (mm) it is invisible; on a clean one (noise-free data from
an independent integrator, a very precise sensor) it is the whole residual, and a likelihood that
calls the residual white noise of an inferred ``sigma_x`` is then over-confident: ``sigma_x``
drops to the error's size (~1 micron) and the posterior is a few 1e-4 log units wide around a
MAP that absorbed the error into the gains, 26-47 posterior std from the truth (measured on
chain2 of ``experiments/default_calibration.py``, linearised at the MAP), and the start
pipeline's importance weights fail (Pareto k_hat 4.1).

What it is. After a MAP fit the error is MEASURED there by step doubling: the rollout with
``2 s`` substeps against the run's ``s``; for a first-order step ``tau_s - tau_exact ~ 2 (tau_s
- tau_2s)``, so ``e_hat = 2 (tau_s - tau_2s)`` [B, T] (m, zero at padded samples). On chain2 it
matches the difference to the independent scipy integration (``tests/test_integration_error.py``:
rms within 10%, correlation > 0.99); the worst case over the prior box (the step choice's
estimate, 0.1 mm) is ~70x larger. It enters every generative likelihood (gaussian, student_t,
ar1, the force-noise MVN) twice:

* as a **known offset** (Richardson extrapolation frozen at the MAP): the residual is taken
  against ``tau_s(theta) - e_hat``, the simulator's output with its measured error removed;
* as a **white floor**: ``sigma_eff^2 = sigma_x^2 + e_rms^2`` with ``e_rms`` the RMS of ``e_hat``
  over the real samples: what the offset leaves (the extrapolation's own error, and the error's
  change away from the MAP) is at most the error itself, so the data are not trusted below it.
  ``e_rms`` is also the lower end of sigma_x's prior (:func:`treeinfer.model.likelihood.
  likelihood_terms`; as the sensor's resolution is otherwise): on clean data sigma_x then sits
  in the prior's steep Gaussian tail just below it, a Gaussian the importance proposal matches,
  instead of at the kink where the quadrature takes over.

Why both (measured on chain2, seed 0, clean, 33 substeps; ``e_rms`` = 1.4 micron): the error is
smooth and aligned with the gains' sensitivities, so the fit absorbs it (the MAP 0.2-0.9% off the
truth in log gains). The floor alone widens the posterior 2x and leaves the truth 12-21 posterior
std away; the offset removes 97% of the error (what is left: 4e-5 mm rms at the truth) and with
the floor the truth lies within 0.7 std of the MAP (linearised; the default command's posterior:
4/4 truths inside, importance weights accepted). On a 2 mm recording both are invisible: the
floor adds ~5e-7 of the variance, the offset moves the residual by 7e-4 of its std and tilts the
log-likelihood by < 0.1 nats across the posterior's bulk (test).

When it applies: ``treeinfer infer`` with a generative likelihood, ``sigma_x`` inferred, the
paper's dynamic model without observation channels and the start pipeline (``--init auto``, the
default, or ``importance``): :mod:`treeinfer.inference.integration_floor` fits the MAP, measures
``e_hat`` there and builds the final problem with it; the run's log, ``summary.json`` and
``problem.settings["integration_error"]`` say its size; the predictive band adds ``e_rms`` in
quadrature (its rollouts are not corrected). Not corrected: the velocity term (off by default).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError

__all__ = ["IntegrationError", "corrected_residual", "floored_scale"]


class IntegrationError(NamedTuple):
    """The simulator's measured discretisation error at a reference point (module docstring).

    shape: ``[B, T]`` m, ``2 (tau_s - tau_2s)`` of the training pulls (zero at masked samples).
    rms: m, its root mean square over the real samples (the white floor).
    substeps: ``s``, the run's simulation steps per observation (compared with ``2 s``).
    reference: ``[2R]`` log gains where it was measured (the MAP).
    """

    shape: np.ndarray
    rms: float
    substeps: int
    reference: np.ndarray

    @classmethod
    def from_rollouts(cls, tau_s, tau_2s, mask, substeps: int, reference):
        """From the rollouts ``tau_s``, ``tau_2s`` [B, T] (m) at ``reference`` with ``substeps``
        and twice as many steps per observation."""
        mask = np.asarray(mask, bool)
        e = np.where(mask, 2.0 * (np.asarray(tau_s, float) - np.asarray(tau_2s, float)), 0.0)
        if not np.all(np.isfinite(e)):
            raise ConfigError("integration error: the step-doubling rollouts are not finite")
        n = max(int(mask.sum()), 1)
        rms = float(np.sqrt(np.sum(e**2) / n))
        ref = np.asarray(reference, float).reshape(-1)
        return cls(e, rms, int(substeps), ref)

    def padded(self, shape) -> np.ndarray:
        """``shape`` ``[B', T']`` (a shape bucket): the error shape with zeros at padded rows and
        steps (no data there)."""
        b, t = np.shape(self.shape)
        out = np.zeros(tuple(int(n) for n in shape))
        out[:b, :t] = self.shape
        return out

    def describe(self) -> str:
        return (
            f"integration error {self.rms * 1e3:.3g} mm rms (step doubling at the MAP: "
            f"{self.substeps} vs {2 * self.substeps} substeps per observation), removed from the "
            f"simulated displacement and added to sigma_x in quadrature as a floor"
        )

    def settings(self) -> dict:
        """JSON-ready record (the run's ``problem.settings["integration_error"]``)."""
        return {
            "rms_m": self.rms,
            "max_abs_m": float(np.max(np.abs(self.shape))) if np.size(self.shape) else 0.0,
            "substeps": self.substeps,
            "reference": [float(x) for x in self.reference],
            "rule": "step doubling at the MAP: e = 2 (tau_s - tau_2s); the residual is taken "
            "against tau_s - e and sigma_eff^2 = sigma_x^2 + rms(e)^2",
        }


def floored_scale(sigma, floor: float | None):
    """``sqrt(sigma^2 + floor^2)`` (jnp; ``floor`` m or None: ``sigma`` unchanged)."""
    if floor is None or floor <= 0.0:
        return sigma
    return jnp.sqrt(jnp.asarray(sigma) ** 2 + float(floor) ** 2)


def corrected_residual(dx, mask, shape):
    """``dx + e`` (recorded minus the simulated displacement with its measured error ``e``
    removed), zero where ``mask`` [B, T] is False; ``dx`` [N, B, T], ``shape`` ``e`` [B, T]."""
    mask = jnp.asarray(mask, bool)
    return jnp.where(mask, jnp.asarray(dx) + jnp.asarray(shape, jnp.asarray(dx).dtype), 0.0)


def check_integration_error(ie, shape) -> IntegrationError | None:
    """``ie`` (None or an :class:`IntegrationError`) checked against the data's ``[B, T]``."""
    if ie is None:
        return None
    if not isinstance(ie, IntegrationError):
        raise ConfigError("integration_error: expected a treeinfer IntegrationError or None")
    if tuple(np.shape(ie.shape)) != tuple(shape):
        raise ConfigError(
            f"integration_error: measured on pulls of shape {np.shape(ie.shape)}, the data have "
            f"{tuple(shape)}"
        )
    if not (math.isfinite(ie.rms) and ie.rms >= 0.0):
        raise ConfigError(f"integration_error: rms must be finite and >= 0, got {ie.rms!r}")
    return ie
