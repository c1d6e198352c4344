"""The batched SBC programs: one jitted function runs a sampler on C data sets at once.

``smc`` (default): tempered SMC from exact prior draws (:mod:`treeinfer.calibration.smc`);
likelihood only, one simulation per particle and step. ``mh``: the previous sampler, kept for
comparison (Adam ascent of P starts with central-difference gradients, then random-walk MH
chains from the best mode; it stays in a wrong local mode for some data sets). ``svgd``: final
SVGD particles (measures SVGD's own calibration).
"""

from __future__ import annotations

import math

import numpy as np

from .config import SBCConfig

_WARMUP_PHASES = 4  # MH warm-up phases (proposal covariance re-estimated at each start)


def build_program(sim, tree, config: SBCConfig, dim: int):
    """The jitted ``(keys [C], theta0 [C, P, D], forces [C, B, T], x_obs [C, B, T]) ->
    (draws [C, L, D], info)``: the sampler's whole scan ``vmap``-ed over C data sets.

    ``theta0``: for ``smc`` N = ``smc_particles`` exact prior draws per data set (L =
    ``particles`` of the final cloud are returned); otherwise P = L starts in the prior box.
    theta columns: log Kp, log Kd of the R inferred joints, then log sigma_x (m) if inferred."""
    import jax
    import jax.numpy as jnp
    import optax

    from ..inference.samplers import svgd
    from ..model import noise as _noise
    from ..model.gradients import autodiff_value_and_grad, finite_difference_jvp
    from ..model.likelihood import gains_from_theta
    from ..model.priors import smoothed_box
    from ..sim import simulate
    from .smc import tempered_smc

    r = sim.n_joints
    lo, hi = np.log(tree.bounds_array()[0]), np.log(tree.bounds_array()[1])
    box = smoothed_box(lo, hi, config.prior_sigma * (hi - lo))
    infer_sigma = config.noise_displacement is None
    sigma_prior = (
        _noise.log_sigma_prior(config.noise_prior_center, config.sigma_prior_scale)
        if infer_sigma
        else None
    )
    kind, df = config.likelihood, float(config.student_t_df)
    n_mh = int(config.mh_steps)
    n_warm = int(config.mh_warmup)

    def rollout_of(forces):
        def rollout(th):  # black box [M, 2R] -> tau [M, B, T] (NaN where unstable)
            kp, kd = gains_from_theta(th, r)
            ro = simulate(sim, kp, kd, forces)
            return jnp.where(ro.stable[..., None], ro.tau, jnp.nan)

        return rollout

    def log_prior(theta):  # [P, D] -> [P]
        lp = box(theta[:, : 2 * r])
        return lp + sigma_prior(theta[:, 2 * r]) if infer_sigma else lp

    def log_lik_of_tau(theta, tau, x_obs):  # -> [P], -inf where unstable
        if infer_sigma:
            sx = jnp.exp(theta[:, 2 * r])
        else:
            sx = jnp.full(theta.shape[:1], config.noise_displacement, tau.dtype)
        res = _noise.residual_log_prob(x_obs - tau, sx[:, None, None], kind, df)
        ll = jnp.sum(res, (-2, -1))
        return jnp.where(jnp.isfinite(ll), ll, -jnp.inf)

    def log_density(theta, forces, x_obs):  # theta [P, D] -> [P]
        tau = finite_difference_jvp(rollout_of(forces), config.rel_step)(theta[:, : 2 * r])
        total = log_lik_of_tau(theta, tau, x_obs) + log_prior(theta)
        return jnp.where(jnp.isfinite(total), total, -jnp.inf)

    def one(key, theta0, forces, x_obs):
        if config.sampler == "smc":
            rollout = rollout_of(forces)

            def log_lik(th):
                return log_lik_of_tau(th, rollout(th[:, : 2 * r]), x_obs)

            k_smc, k_pick = jax.random.split(key)
            x, smc_info = tempered_smc(
                k_smc,
                theta0,
                log_prior,
                log_lik,
                n_levels=config.smc_levels,
                n_mutations=config.smc_mutations,
                n_final=config.smc_final,
                target_ess=config.smc_target_ess,
            )
            # L of the N final particles, at random (the cloud's order carries ancestry)
            x = x[jax.random.permutation(k_pick, x.shape[0])[: config.particles]]
            ld = log_lik(x) + log_prior(x)
            info = {f"smc_{k}": v for k, v in smc_info._asdict().items()}
        else:
            logp = lambda th: log_density(th, forces, x_obs)  # noqa: E731
            vg = autodiff_value_and_grad(logp)
            if config.sampler == "svgd":
                algo = svgd(vg, learning_rate=config.learning_rate)
                state = algo.init(key, theta0)
                state, _ = jax.lax.scan(
                    lambda s_, _: algo.step(key, s_), state, None, length=config.iterations
                )
                x, ld = state.position, state.logdensity
                info = {"mode_logdensity": jnp.max(ld)}
            else:
                x, ld, info = _ascent_then_mh(key, logp, vg, theta0)
        info["final_mean_logdensity"] = jnp.mean(jnp.where(jnp.isfinite(ld), ld, jnp.nan))
        info["n_nonfinite"] = jnp.sum(~jnp.isfinite(ld))
        return x, info

    def _ascent_then_mh(key, logp, vg, theta0):
        # 1. Adam ascent of the P starts (independent, no kernel), learning rate decaying
        #    10x..100x so the particles settle on their modes; the best one is the mode.
        sched = optax.exponential_decay(config.learning_rate, config.iterations, 0.01)
        opt = optax.adam(sched)

        def ascend(carry, _):
            th, st = carry
            _, g = vg(th)
            upd, st = opt.update(-g, st, th)
            return (optax.apply_updates(th, upd), st), None

        (th, _), _ = jax.lax.scan(
            ascend, (theta0, opt.init(theta0)), None, length=config.iterations
        )
        ld0 = logp(th)
        ld0 = jnp.where(jnp.isfinite(ld0), ld0, -jnp.inf)
        best = th[jnp.argmax(ld0)]
        # 2. P random-walk MH chains from the mode (+ a tiny jitter). Warm-up in phases: the
        #    proposal is exp(log_s) * chol(ensemble covariance of the chains), re-estimated at
        #    each phase start (first phase: 0.01 * I), log_s tuned to ~25% acceptance by a
        #    Robbins-Monro step on the chains' mean acceptance. Then mh_steps steps with a fixed
        #    proposal; the final state of every chain is one draw.
        k0, k1, k2 = jax.random.split(jax.random.fold_in(key, 7), 3)
        x = best + 1e-3 * jax.random.normal(k0, theta0.shape, theta0.dtype)
        ld = logp(x)
        ld = jnp.where(jnp.isfinite(ld), ld, -jnp.inf)

        def mh_step(carry, k, adapt):
            xs, lds, chol, log_s, n_acc = carry
            ka, kb = jax.random.split(k)
            step = jnp.exp(log_s) * (jax.random.normal(ka, xs.shape, xs.dtype) @ chol.T)
            xp = xs + step
            ldp = logp(xp)
            ldp = jnp.where(jnp.isfinite(ldp), ldp, -jnp.inf)
            ok = jnp.log(jax.random.uniform(kb, lds.shape, xs.dtype)) < ldp - lds
            rate = jnp.mean(ok)
            log_s = log_s + adapt * 0.5 * (rate - 0.25)
            return (
                jnp.where(ok[:, None], xp, xs),
                jnp.where(ok, ldp, lds),
                chol,
                log_s,
                n_acc + rate,
            ), None

        def run(carry, keys, adapt):
            return jax.lax.scan(lambda c, k: mh_step(c, k, adapt), carry, keys)[0]

        def ensemble_chol(xs):
            c = jnp.cov(xs.T) + 1e-12 * jnp.eye(dim)
            return jnp.linalg.cholesky(c)

        carry = (x, ld, 0.01 * jnp.eye(dim, dtype=x.dtype), jnp.zeros((), x.dtype), jnp.zeros(()))
        n_phase = max(1, n_warm // _WARMUP_PHASES)
        for i, kw in enumerate(jax.random.split(k1, _WARMUP_PHASES)):
            if i > 0:
                carry = (
                    carry[0],
                    carry[1],
                    ensemble_chol(carry[0]),
                    jnp.asarray(math.log(2.38 / math.sqrt(dim)), x.dtype),
                    carry[4],
                )
            carry = run(carry, jax.random.split(kw, n_phase), 1.0)
        carry = (carry[0], carry[1], ensemble_chol(carry[0]), carry[3], jnp.zeros(()))
        x, ld, _, log_s, n_acc = run(carry, jax.random.split(k2, n_mh), 0.0)
        info = {
            "mh_acceptance": n_acc / max(n_mh, 1),
            "mode_logdensity": jnp.max(ld0),
            "mh_log_scale": log_s,
        }
        return x, ld, info

    return jax.jit(jax.vmap(one))
