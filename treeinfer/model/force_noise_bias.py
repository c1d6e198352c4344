"""The errors-in-variables bias correction of the force-noise likelihood
(:mod:`treeinfer.model.force_noise`).

The simulator is driven by the RECORDED force, so the residual at theta holds ``-J(theta) eps``
(the model's response to the recorded noise ``eps``, which the branch never felt), and its
expected weighted square grows with ``tr(Sigma^-1 C(theta))``: with ``C`` fixed at ``theta_ref``
the fit prefers gains whose response to force noise is small (stiffer, more damped), a bias of
several posterior widths and a posterior too narrow for its Cramer-Rao bound. On the independent
chain2 case of ``experiments/default_calibration.py`` (seed 0, 2% force noise) the truth sat
14.2 nats below the maximum of the 5-parameter posterior (about 2.5 expected); 43-73% of true
values lay inside their 95% intervals over 17 runs.

The corrected score of errors-in-variables models (Nakamura 1990) adds back that expectation's
theta-dependent part, ``+ 1/2 tr(Sigma^-1 (C(theta) - C(theta_ref)))``, whose expected value
cancels the bias to first order and leaves sigma_x's estimate unbiased (only the DIFFERENCE
from the reference is added: the whole trace would bias sigma_x low). It is linear in
``d_i(theta) = u_i^T C(theta) u_i``, the force-induced variance along each eigenvector of
``C(theta_ref)``; :func:`with_bias_slope` takes ``d_i``'s slope in the log gains by forward
differences of ``J`` (2R more runs of the Jacobian's compiled program) and
:func:`treeinfer.model.force_noise.mvn_log_prob` adds
``1/2 sum_i slope_i . (theta - theta_ref) / (L_i + sigma_x^2)``. On that example the truth
then sits 3.5 nats below the maximum. First order only: within ~0.05 in log gain of the
reference it matches the exact trace to 3% (``tests/test_force_noise.py``), at 0.2 it is only
indicative (0.19 against 0.09 nats), so a posterior far from the reference is corrected roughly.
"""

from __future__ import annotations

import numpy as np

from .force_noise import BIAS_STEP, ForceNoiseBasis, force_jacobian

__all__ = ["with_bias_slope"]


def with_bias_slope(
    sim, basis: ForceNoiseBasis, theta_ref, forces, sigma_force: float, mask=None,
    grasp_fraction=None, h: float = BIAS_STEP,
) -> ForceNoiseBasis:  # fmt: skip
    """``basis`` with the bias correction's slope (module docstring): ``slope[b, i, j]``
    ``= d/d theta_j (u_i^T C_b(theta) u_i)`` at ``theta_ref``, by forward differences of
    :func:`force_jacobian` (forward, step ``h`` in log gain; the same compiled program as ``J``)."""
    ref = np.asarray(theta_ref, float).reshape(-1)
    forces = np.atleast_2d(np.asarray(forces, float))
    m = np.ones(forces.shape, bool) if mask is None else np.asarray(mask, bool)
    u = np.asarray(basis.vectors, float)

    def along(theta):  # [B, T]: u_i^T C(theta) u_i = sigma_F^2 |J^T u_i|^2
        j = force_jacobian(sim, theta, forces, grasp_fraction, keep=False)
        j = j * m[:, :, None] * m[:, None, :]
        return float(sigma_force) ** 2 * np.sum(np.einsum("bts,bti->bsi", j, u) ** 2, axis=1)

    # forward differences from the reference, where u_i^T C u_i = L_i exactly: 2R Jacobians
    # instead of central differences' 4R (each a forward-mode pass of T tangents, about 5 s per
    # pull set on two CPU cores for 3 pulls of 300 samples); the O(h) error is below the first
    # order's own beyond a few h (module docstring)
    lam = np.asarray(basis.values, float)
    eye = np.eye(ref.size)
    slope = np.stack([(along(ref + h * eye[k]) - lam) / h for k in range(ref.size)], axis=-1)
    return basis._replace(slope=slope, theta_ref=ref)
