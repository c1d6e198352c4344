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
differences of ``J`` (2R more runs of the Jacobian's compiled program).

What the likelihood adds is the STANDARDISED form of that correction
(:func:`treeinfer.model.force_noise.mvn_log_prob`): each direction's residual ``z_i = u_i^T r``
is weighed by the variance at theta, ``d_i(theta) + sigma_x^2`` (first order in the log gains,
floored at zero), with the normalisation kept at the reference:

    log p = sum_i log N(z_i; 0, L_i + s^2) + 1/2 sum_i z_i^2 (1/(L_i + s^2) - 1/(d_i(theta) + s^2)).

Its expectation over the noise is the same for every theta (the bias is gone, as with the
corrected score), and to first order at a typical residual (``z_i^2 = L_i + s^2``) it IS the
corrected score. The difference: the corrected score adds ``1/2 sum (d_i - L_i)/(L_i + s^2)``
whatever the residual, so gains with a large response to the force noise (a weakly damped
child that rings) gained density from the correction alone, and the fluctuation of the
quadratic term is largest exactly there: the posterior's maximum drifted toward them (chain2
of ``experiments/default_calibration.py``: the child's damping at the box's lower edge in a
third of the runs, where the stiffnesses look twice as well identified as at the truth;
60-74% of true values inside their 95% intervals). The standardised form rewards a large
``d_i`` only where the residual along ``u_i`` is actually large. On chain2 seed 0 the truth
sat 14.1 nats below the maximum uncorrected and 4.5 with the corrected score
(``experiments/eiv_bias.py``). First order only: within ~0.05 in log gain of the reference
``d_i`` matches the exact value to 3% (``tests/test_force_noise.py``); at 0.2 it is only
indicative, and beyond :data:`treeinfer.model.force_noise.BIAS_TRUST` it is held, so the
start pipeline takes the reference again at a MAP that moved
(:func:`treeinfer.inference.start_pipeline.force_noise_reference`).
"""

from __future__ import annotations

import numpy as np

from .force_noise import BIAS_STEP, ForceNoiseBasis, _basis_key, force_jacobian

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
    # kept on the simulator (a run's reference problem and its final problem take the same
    # slope: 2R Jacobians each time), keyed by every input and the basis it projects on
    key = _basis_key(
        sim, "slope", ref, forces, sigma_force, m, grasp_fraction, float(h), lam.tobytes(),
        u.tobytes(),
    )  # fmt: skip
    kept = sim.derived.setdefault("force_noise_slopes", {})
    if key not in kept:
        from ..sim.threads import map_calls

        # the 2R Jacobians are independent: on the idle cores (the same values, sooner)
        steps = ref + h * np.eye(ref.size)
        slope = np.stack([(a - lam) / h for a in map_calls(along, steps)], axis=-1)
        if len(kept) >= 2:  # the last two: a run linearises again at most a few times
            kept.pop(next(iter(kept)))
        kept[key] = slope
    return basis._replace(slope=kept[key].copy(), theta_ref=ref)
