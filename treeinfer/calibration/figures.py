"""Figures of a tree SBC beyond the ranks: posterior std / Cramer-Rao bound and the share of
noisy unseen test points inside the 95% predictive band."""

from __future__ import annotations

import math

import numpy as np

from .config import SBCConfig


def _rollout_fn(sim, r):
    from ..model.likelihood import gains_from_theta
    from ..sim import simulate

    def rollout(th, f):  # th [M, >=2R], f [B, T] -> (tau [M, B, T], stable [M, B])
        kp, kd = gains_from_theta(th[:, : 2 * r], r)
        ro = simulate(sim, kp, kd, f)
        return ro.tau, ro.stable

    return rollout


def _crb_ratios(sim, truth, draws, forces_rec, labels, config: SBCConfig) -> dict:
    """Posterior std (log units, over the draws) / Cramer-Rao std at the truth, per parameter:
    median and quartiles over data sets. Fisher of the gains ``J^T J / sigma^2`` with ``J`` the
    central-difference sensitivities of the training displacements to the log gains under the
    recorded forces (:func:`treeinfer.model.gradients.central_difference_jacobian`); for log sigma_x
    (Gaussian) the bound is ``1 / sqrt(2 n)`` (n samples; the Fisher matrix is block diagonal).
    Only for the Gaussian likelihood (None otherwise)."""
    import jax
    import jax.numpy as jnp

    from ..model.gradients import central_difference_jacobian

    if config.likelihood != "gaussian":
        return {"crb": None}
    r = sim.n_joints
    rollout = _rollout_fn(sim, r)

    def jac_one(th, f):
        _, j = central_difference_jacobian(
            lambda t: rollout(t, f)[0], th[None, : 2 * r], rel_step=1e-2
        )
        return j[0]  # [B, T, 2R]

    fn = jax.jit(jax.vmap(jac_one))
    n = truth.shape[0]
    crb = np.empty((n, truth.shape[1]))
    for start in range(0, n, config.chunk):
        sl = slice(start, min(n, start + config.chunk))
        j = np.asarray(fn(jnp.asarray(truth[sl]), jnp.asarray(forces_rec[sl])), float)
        j = j.reshape(j.shape[0], -1, 2 * r)
        sig = (
            np.exp(truth[sl, 2 * r])
            if config.noise_displacement is None
            else np.full(j.shape[0], config.noise_displacement)
        )
        for i in range(j.shape[0]):
            fisher = j[i].T @ j[i] / sig[i] ** 2
            crb[sl.start + i, : 2 * r] = np.sqrt(np.diag(np.linalg.pinv(fisher)))
        if config.noise_displacement is None:
            crb[sl, 2 * r] = 1.0 / math.sqrt(2 * j.shape[1])
    ratio = np.std(draws, axis=1, ddof=1) / crb
    q = np.nanpercentile(ratio, [25, 50, 75], axis=0)
    return {
        "crb": {
            "definition": "posterior std of the log parameter over the draws / Cramer-Rao std at "
            "the truth (Fisher J^T J / sigma^2, J by central differences on the recorded training "
            "forces; log sigma_x: 1/sqrt(2n)); quartiles over data sets",
            "parameters": {
                lab: {
                    "ratio_q25": float(q[0, k]),
                    "ratio_median": float(q[1, k]),
                    "ratio_q75": float(q[2, k]),
                    "crb_log_std_median": float(np.median(crb[:, k])),
                }
                for k, lab in enumerate(labels)
            },
        }
    }


def _predictive_coverage(sim, draws, test, config: SBCConfig, infer_sigma: bool) -> dict:
    """Share of noisy unseen test points inside the 95% predictive band (draws' simulations
    under the recorded test forces + their noise model) and inside the parameter-only band,
    per data set (median, quartiles, pooled)."""
    import jax
    import jax.numpy as jnp

    from ..evaluation.metrics import predictive_bands

    f_test, x_test, st_truth = test
    r = sim.n_joints
    fn = jax.jit(jax.vmap(_rollout_fn(sim, r)))
    n = draws.shape[0]
    inside_pred = np.full(n, np.nan)
    inside_par = np.full(n, np.nan)
    for start in range(0, n, config.chunk):
        sl = slice(start, min(n, start + config.chunk))
        tau, stable = fn(jnp.asarray(draws[sl]), jnp.asarray(f_test[sl]))
        tau, stable = np.asarray(tau), np.asarray(stable)
        for i in range(tau.shape[0]):
            d = sl.start + i
            valid = np.all(stable[i], axis=-1)
            if valid.sum() < 2 or not np.all(st_truth[d]):
                continue
            s = np.exp(draws[d, :, 2 * r]) if infer_sigma else float(config.noise_displacement)
            kind = "student_t" if config.likelihood == "student_t" else "gaussian"
            bands = predictive_bands(tau[i], s, 0.95, valid, kind, float(config.student_t_df))
            x = x_test[d]
            inside_pred[d] = np.mean(
                (x >= np.asarray(bands.predictive.lower))
                & (x <= np.asarray(bands.predictive.upper))
            )
            inside_par[d] = np.mean(
                (x >= np.asarray(bands.parameter.lower)) & (x <= np.asarray(bands.parameter.upper))
            )

    def stats(v):
        q = np.nanpercentile(v, [25, 50, 75])
        return {
            "mean": float(np.nanmean(v)),
            "q25": float(q[0]),
            "median": float(q[1]),
            "q75": float(q[2]),
            "n_datasets": int(np.sum(np.isfinite(v))),
        }

    return {
        "test_inside_95": {
            "definition": f"share of the {config.test_traj} noisy unseen test pulls' points inside "
            "the 95% band per data set; predictive = simulations + fitted noise "
            "(metrics.predictive_bands), parameter = simulations only",
            "noise_force_share": config.noise_force,
            "predictive": stats(inside_pred),
            "parameter": stats(inside_par),
        }
    }
