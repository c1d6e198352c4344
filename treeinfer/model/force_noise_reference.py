"""The reference point of the force-noise term: where the force Jacobian ``J`` (and with it
``C``) is taken, :func:`reference_theta` (see :mod:`treeinfer.model.force_noise` for why the MAP).
Separate from :mod:`treeinfer.model.force_noise` for its size (issue 26); ``treeinfer.model``
exports it as before (``treeinfer.model.reference_theta``)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..data.trajectories import Observations
from ..errors import ConfigError, SimulationError
from .force_noise import force_noise_basis

__all__ = ["reference_theta"]


def reference_theta(
    sim, obs: Observations, grasp_fraction=None, sigma_force=None, n_starts: int = 8, seed=0
):
    """``theta_ref [2R]`` (log Kp, log Kd) at which the force Jacobian is taken.

    1. The MAP of the Gaussian displacement model with sigma_x fitted and no force term, by
       Levenberg-Marquardt (:func:`treeinfer.inference.mapfit.fit_map`) from ``n_starts``
       Latin-hypercube points of the simulator's prior box.
    2. With ``sigma_force`` (N): the MAP of the errors-in-variables model itself, its covariance
       ``C`` taken at step 1's point and sigma_x fixed at the data's white-noise estimate
       (:func:`treeinfer.model.noise.estimate_displacement_noise`), LM on the whitened residuals
       ``diag(1 / sqrt(L + sigma_x^2)) U^T r`` from every final point of step 1. Step 1's model
       is misspecified (the slow force-induced error is taken as white), and on the 3-branch
       example its MAP lies in another mode (child stiffness off by a factor 1.5).

    Both fits use a prior flat inside the box with Gaussian walls outside (scale 5% of each
    log-box width) and the result is clipped to the box: without the walls a weakly identified
    damping runs off to exp(-27) (an undamped reference: a ringing J). See the module docstring
    for why the MAP."""
    from ..inference.mapfit import ResidualModel, fit_map, gaussian_residuals
    from .noise import estimate_displacement_noise

    lo, hi = (np.log(np.asarray(b, float)) for b in sim.prior_box)
    wall = 0.05 * (hi - lo)

    def box_walls(theta):  # [P, 2R] -> [P]; 0 inside the box
        th = theta[:, : lo.size]
        out = jnp.maximum(lo - th, 0.0) + jnp.maximum(th - hi, 0.0)
        return -0.5 * jnp.sum((out / wall) ** 2, axis=-1)

    first = fit_map(
        gaussian_residuals(sim, obs, None, grasp_fraction),
        box_walls,
        lo,
        hi,
        n_starts=n_starts,
        seed=seed,
        agree=3,
    )
    theta = np.clip(np.asarray(first.theta[: lo.size], float), lo, hi)
    if sigma_force is not None:
        try:
            sx = estimate_displacement_noise(obs).sigma
        except ConfigError:
            sx = float(np.exp(first.theta[-1]))
        mask = np.asarray(obs.mask, bool)
        basis = force_noise_basis(sim, theta, obs.force, sigma_force, mask, grasp_fraction)
        white = basis.vectors / np.sqrt(basis.values + sx**2)[:, None, :]  # [B, T, T]
        base = gaussian_residuals(sim, obs, 1.0, grasp_fraction)  # r = tau - x, masked

        def whitened(th):
            r, ok = base.residuals(th)
            return jnp.einsum("bts,bt->bs", jnp.asarray(white, r.dtype), r), ok

        finals = np.clip(first.finals[:, : lo.size], lo, hi)
        finals = finals[np.isfinite(first.values)]
        second = fit_map(
            ResidualModel(whitened, "gaussian"), box_walls, lo, hi, starts=finals, agree=3
        )
        theta = np.clip(np.asarray(second.theta[: lo.size], float), lo, hi)
    if not np.all(np.isfinite(theta)):
        raise SimulationError("force noise: the reference MAP fit did not give finite gains")
    return theta
