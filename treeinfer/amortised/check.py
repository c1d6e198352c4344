"""The amortised posterior checked on the spot, and the run layer's start built from it.

Four steps, in order, before a flow's answer is trusted:

1. **Domain.** Each pull's largest force and displacement and its two noise estimates must lie
   in the training recordings' range (their 0.1-99.9% quantiles, recorded at training) widened
   by :data:`DOMAIN_MARGIN`: a recording outside it (a force ten times the trained peaks, a
   stiffer branch than the prior allows) is one the network never saw; its answer is not
   looked at.
2. **Importance weights.** ``M`` draws of the flow ``q`` are weighted by ``p / q`` with ``p``
   the simulator-based posterior's own log-density (the run's problem: likelihood, noise model
   and priors; one batched rollout per chunk of draws) and Pareto-smoothed
   (:func:`treeinfer.inference.importance.importance_resample`, ``psis`` = ``arviz.psislw``).
   ``k_hat <= 0.7`` and an effective sample size of at least a quarter of the particles: the
   resampled draws are the posterior (exact up to importance-sampling error, whatever the
   flow's own error).
3. **Refinement.** A flow trained on 10^4 simulations is calibrated but wider than the
   posterior (3-10x in log Kp on a few pulls at 2 mm noise: its weights degenerate, k_hat 2-8).
   Up to :data:`REFINE_ROUNDS` more rounds of population Monte Carlo (Cappe et al. 2004) draw
   :data:`REFINE_DRAWS` each from a Student-t: the first round's at the mode of the start
   pipeline's batched LM fit from the best draws (:func:`_lm_proposal`), later ones' at the
   weighted draws' moments; every draw so far is reweighted against the deterministic
   mixture of the flow and the rounds' proposals (Owen & Zhou 2000: unbiased for any
   proposals, a draw of a poor round cannot get an extreme weight where a later proposal
   covers it). The rounds stop once the weights pass
   with an effective sample size of :data:`TARGET_ESS_SHARE` of the particles. If they still
   fail, the flow is off for this recording.
4. **Predictive.** The checked posterior's displacement noise ``sigma_x`` against the
   recording's own noise estimate (:func:`predictive_reasons`): the training sets' ratio, as
   for the domain. A recording the simulator cannot fit (a logger's delay, another tree) gets
   a posterior whose noise soaks up the misfit: exact for the model, but not an answer to
   give without the simulator-based path's fit verdict.

When a check fails, :func:`amortised_start` returns no posterior and the run goes the
simulator-based way (``--init auto``: screen, MAP fit, importance, the sampler if needed),
saying so; the report lands in summary.json under ``amortised``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

DOMAIN_MARGIN = 0.25  # share of the training range's width added on each side
DEFAULT_DRAWS = 1024  # flow draws weighted (PSIS k_hat needs several hundred to be reliable)
CHUNK = 256  # draws per log-density call (one compiled shape)
REFINE_ROUNDS = 3  # population Monte Carlo rounds after the flow's, at most
REFINE_DRAWS = 256  # draws per round (one compiled chunk)
REFINE_DF = 5.0  # the rounds' Student-t: heavier tails than the moments' Gaussian
REFINE_INFLATE = 1.5  # the rounds' scale over the weighted draws' (a degenerate round is narrow)
LM_STARTS = 4  # best draws the first refinement round's LM fit starts from
LM_ITERATIONS = 30  # as the start pipeline's fit
NEWTON_STEPS = 4  # Newton steps per refinement round (stencil calls), at most
STEP_FLOOR = 1e-4  # smallest difference step of the Hessian (log units: float32's noise below)
TARGET_ESS_SHARE = 1.0  # stop refining at an effective sample size of the particles' number


def domain_reasons(am, feats: np.ndarray) -> list[str]:
    """Why the recording's features (``[B, F]``) lie outside the training range (empty: inside):
    its pulls' force and displacement amplitudes and noise estimates, each against the range
    recorded at training, widened by :data:`DOMAIN_MARGIN` of its width (in log units)."""
    from .estimator import FEATURE_TAIL

    env = am.meta.get("training", {}).get("feature_envelope")
    if not env:
        return []
    f_scale, x_scale = am.meta["scales"]
    what = {
        "log_force": ("largest |force|", "N", f_scale),
        "log_displacement": ("largest |displacement|", "m", x_scale),
        "log_force_noise": ("force noise", "N", f_scale),
        "log_disp_noise": ("displacement noise", "m", x_scale),
    }
    out = []
    for key, j in FEATURE_TAIL.items():
        lo, hi = env[key]
        pad = DOMAIN_MARGIN * (hi - lo)
        v = feats[:, j]
        bad = np.flatnonzero((v < lo - pad) | (v > hi + pad))
        if bad.size:
            i = int(bad[0])
            name, unit, s = what[key]
            lo_s, hi_s = s * math.exp(lo), s * math.exp(hi)
            out.append(
                f"pull {i + 1}: {name} {s * math.exp(v[i]):.3g} {unit} outside the "
                f"training range {lo_s:.3g}-{hi_s:.3g} {unit}"
            )
    return out


def predictive_reasons(am, feats: np.ndarray, log_sigma_x) -> list[str]:
    """Why the checked posterior does not explain the recording as the training sets were
    explained (empty: it does): its median ``sigma_x`` against the recording's own displacement
    noise estimate (:func:`~treeinfer.amortised.estimator.noise_ratio`), which must lie in the
    training sets' range of that ratio widened by :data:`DOMAIN_MARGIN` of its width. A
    recording the simulator fits up to white noise has a ratio near 1; one it cannot fit (a
    logger's delay, another tree, a drift) has a posterior noise that soaks up the misfit, and
    the fast answer is not trusted where the simulator-based path would report a poor fit."""
    from .estimator import noise_ratio

    env = am.meta.get("training", {}).get("noise_ratio_envelope")
    if not env:
        return []
    lo, hi = env
    pad = DOMAIN_MARGIN * (hi - lo)
    med = float(np.median(np.asarray(log_sigma_x, float)))
    r = float(noise_ratio(np.array([med]), feats[None], am.meta["scales"][1])[0])
    if lo - pad <= r <= hi + pad:
        return []
    return [
        f"posterior predictive check: the fit's displacement noise sigma_x {math.exp(med):.3g} m "
        f"is {math.exp(r):.3g} times the recording's own noise estimate (training range "
        f"{math.exp(lo):.2g}-{math.exp(hi):.2g}): the simulator does not explain this recording "
        "as it explained the training ones"
    ]


def _log_density(problem, draws: np.ndarray) -> np.ndarray:
    import jax.numpy as jnp

    dtype = jnp.asarray(0.0).dtype
    m = len(draws)
    padded = np.concatenate([draws, np.repeat(draws[-1:], (-m) % CHUNK, axis=0)])
    out = [
        np.asarray(problem.log_density(jnp.asarray(padded[i : i + CHUNK], dtype)), float)
        for i in range(0, len(padded), CHUNK)
    ]
    return np.concatenate(out)[:m]


def refine(am, problem, feats, draws, log_q, n_particles: int, seed: int = 0, log=None):
    """``(ImportancePosterior, index [n_particles])``: the flow's ``draws`` (log density
    ``log_q``) weighted against ``problem``'s posterior, then up to :data:`REFINE_ROUNDS`
    population Monte Carlo rounds (module docstring) while the weights fail or their effective
    sample size is under :data:`TARGET_ESS_SHARE` of ``n_particles``.

    Written here rather than with :class:`treeinfer.inference.importance.PopulationRounds`:
    its mixture holds Gaussian and Student-t proposals only, and the flow (whose density is
    one more network pass, not a closed form) must stay in it: without the flow's component,
    a flow draw's weight against the rounds' mixture is unbounded where the rounds do not
    reach."""
    from ..inference.importance import (
        KHAT_LIMIT,
        ImportancePosterior,
        _draw_log_density,
        importance_resample,
    )

    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x7E]))
    ev = _evaluator(problem, getattr(am, "programs", None))
    density = ev.log_density if ev is not None else (lambda th: _log_density(problem, th))
    xs, lps, sizes, props = [draws], [density(draws)], [len(draws)], []
    lq_flow = [np.asarray(log_q, float)]  # the flow's density, one network pass per round
    target = TARGET_ESS_SHARE * n_particles
    while True:
        x, lp = np.concatenate(xs), np.concatenate(lps)
        # the deterministic mixture: sum_r n_r q_r(x) / sum_r n_r over the flow and the rounds
        comps = [np.concatenate(lq_flow)]
        comps += [_draw_log_density(None, m, c, 0, REFINE_DF, x)[1] for m, c in props]
        lq = np.logaddexp.reduce(
            np.stack(comps) + np.log(np.asarray(sizes, float))[:, None], axis=0
        ) - np.log(float(sum(sizes)))
        with np.errstate(over="ignore"):  # PSIS's tail fit at k_hat >> 1 (a first flow round)
            idx, lw, khat, ess, ok, reason = importance_resample(x, lp, lq, n_particles, seed)
        done = (ok and ess >= target) or len(props) >= REFINE_ROUNDS or not np.isfinite(ess)
        if not done:
            if ev is not None and not props:  # the first round: the mode by LM, its curvature
                nxt = _lm_proposal(ev, x, lp)
            elif ev is not None:  # later rounds: the weighted draws' moments (PMC's rule)
                nxt = _moments(x, lw)
            else:
                last = props[-1][1] if props else None
                nxt = _round_proposal(problem, x, lp, lw, last, draws.std(0) + STEP_FLOOR)
            done = nxt is None
        if not done:
            mean, cov = nxt
            xn, _ = _draw_log_density(rng, mean, cov, REFINE_DRAWS, REFINE_DF)
        if done:
            m_last, c_last = props[-1] if props else (x.mean(0), np.cov(x.T))
            imp = ImportancePosterior(
                x[idx], x, lw, lp, float(khat), float(ess), bool(ok), m_last, c_last,
                REFINE_DF if props else math.inf, reason, len(props) + 1,
                np.where(np.isfinite(lp), lp - lq, -np.inf),
            )  # fmt: skip
            return imp, idx
        if log is not None:
            log(
                f"amortised posterior: Pareto k_hat {khat:.2f}, effective sample size {ess:.0f} "
                f"of {len(x)} draws (k_hat <= {KHAT_LIMIT}, ESS >= {target:.0f} wanted): "
                f"refining, round {len(props) + 1} of {REFINE_ROUNDS}"
            )
        props.append((mean, cov))
        xs.append(xn)
        lps.append(density(xn))
        lq_flow.append(am.log_q(xn, feats))
        sizes.append(len(xn))


class _Chunked:
    """``problem`` whose ``log_density`` is evaluated in :data:`CHUNK`-point calls (the shape
    the check compiled), for :func:`treeinfer.inference.laplace.value_hessian`, whose own
    64-point calls would compile the density once more (1-3 s on a 2-core CPU, per run)."""

    def __init__(self, problem):
        self.log_density = lambda th: _log_density(problem, np.asarray(th, float))


def _evaluator(problem, programs=None):
    """The run's rollout program with the observations as arguments
    (:class:`treeinfer.inference.fast_evaluator.BatchEvaluator`, the start pipeline's: its
    log density is ``problem.log_density``), its log-prior, noise density and Gauss-Newton
    programs with the recording's numbers as arguments too
    (:func:`treeinfer.amortised.programs.with_argument_programs`), all kept in ``programs``
    (the model's :class:`~treeinfer.sim.program_cache.ProgramCache`); or None for a problem it
    does not take (then ``problem.log_density`` itself, in :data:`CHUNK`-point calls). Why:
    the problem's own density embeds the recording as constants and compiles for every new one
    (4-7 s on a 2-core CPU, more than the check); these programs compile once per simulator and
    recording shape, and the persistent compile cache keeps them for the next process."""
    from ..errors import ConfigError
    from ..inference.fast_evaluator import BatchEvaluator, default_chunk
    from .programs import with_argument_programs

    try:
        # the start pipeline's rule: the LM's points on a CPU, a whole round on an accelerator
        k = LM_STARTS * (4 * problem.sim.n_joints + 1)  # starts x (2 x gains + 1) points
        ev = BatchEvaluator(problem, default_chunk(k, DEFAULT_DRAWS), programs)
    except (ConfigError, AttributeError, TypeError):
        return None
    return with_argument_programs(ev, programs)


def _moments(x, lw):
    """``(mean, cov)`` of the weighted draws, the covariance times :data:`REFINE_INFLATE`^2,
    or None where it is not positive definite."""
    from ..inference.importance import weighted_moments

    try:
        mean, cov = weighted_moments(x, lw)
        np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        return None
    return mean, cov * REFINE_INFLATE**2


def _lm_proposal(ev, x, lp):
    """``(mode, cov)`` of the next round's Student-t: the Levenberg-Marquardt fit of the
    start pipeline (:func:`treeinfer.inference.fast_fit.fit_map_batched`: the generalised
    Gauss-Newton curvature from the rollouts' residuals, one batched call per iteration) from
    the :data:`LM_STARTS` best draws so far, its covariance ``H^-1`` times
    :data:`REFINE_INFLATE`^2; None if no start simulates. Why LM and not Newton steps on the
    density's values (:func:`_round_proposal`): a posterior 500 times narrower than the flow
    (two joints, 0.3 mm noise) has a curvature of 10^6 nats per unit, and float32's rounding of
    a density of 2000 nats drowns differences at its width; the residuals' Gauss-Newton
    curvature has no such noise. The flow's draws stand in for the pipeline's screen."""
    from ..errors import SimulationError
    from ..inference.fast_fit import fit_map_batched

    order = np.argsort(-np.where(np.isfinite(lp), lp, -np.inf))[:LM_STARTS]
    try:
        fit = fit_map_batched(ev, x[order], max_iterations=LM_ITERATIONS)
    except SimulationError:
        return None
    cov = np.asarray(fit.cov, float)
    if not np.all(np.isfinite(cov)):
        return None
    return np.asarray(fit.theta, float), 0.5 * (cov + cov.T) * REFINE_INFLATE**2


def _stencil(problem, x, h):
    """``(f, g [D], H [D, D])``: the log density at ``x [D]``, its gradient and Hessian by
    central differences of its values with steps ``h [D]``, in one batched call of 1 + 2 D^2
    points (:func:`treeinfer.inference.laplace.value_hessian`'s stencil: values, not the
    likelihood's own finite-difference gradient, at the posterior's scale). Written out here
    because the Newton step needs the centre value and the gradient too, which
    ``value_hessian`` computes and drops."""
    d = x.size
    e = np.eye(d) * h
    pts = [x] + [x + s * e[i] for i in range(d) for s in (1, -1)]
    pairs = [(i, j) for i in range(d) for j in range(i + 1, d)]
    pts += [x + si * e[i] + sj * e[j] for i, j in pairs for si in (1, -1) for sj in (1, -1)]
    f = _log_density(problem, np.stack(pts))
    fp, fm = f[1 : 1 + 2 * d : 2], f[2 : 2 + 2 * d : 2]
    g = (fp - fm) / (2 * h)
    hess = np.diag((fp - 2 * f[0] + fm) / h**2)
    for k, (i, j) in enumerate(pairs):
        pp, pm, mp, mm = f[1 + 2 * d + 4 * k : 5 + 2 * d + 4 * k]
        hess[i, j] = hess[j, i] = (pp - pm - mp + mm) / (4 * h[i] * h[j])
    return float(f[0]), g, hess


def _round_proposal(problem, x, lp, lw, last_cov, top_spread):
    """``(mean, cov)`` of the next round's Student-t, or None: the Laplace approximation of the
    posterior from the best draw so far, by up to :data:`NEWTON_STEPS` Newton steps on the
    log density (:func:`_stencil`'s gradient and Hessian, steps the posterior's current spread,
    at most ``top_spread``, the flow's; a step that lowers the density is halved), its
    covariance times :data:`REFINE_INFLATE`^2. Why not the weighted draws' moments alone
    (population Monte Carlo's rule): with an effective sample size of 5-15 their covariance is
    that of a handful of points, too narrow in some direction, and the rounds stalled at k_hat
    ~1 on a posterior 200 times narrower than the flow; and why a Newton step rather than the
    best draw as the centre: the best of 1000 flow draws lies tens of posterior widths from
    the mode when the flow is a hundred times wider. The moments remain the fallback where the
    Hessian is not negative definite."""
    from ..inference.importance import weighted_moments

    try:
        mean_w, cov_w = weighted_moments(x, lw)
        np.linalg.cholesky(cov_w)
    except np.linalg.LinAlgError:
        return None
    if last_cov is not None:  # the last round's Laplace spread
        spread = np.sqrt(np.diag(last_cov))
    else:  # a tenth of the flow's spread at least: the weighted draws' may be a few points',
        # and steps under the posterior's width drown in float32's rounding of the density
        spread = np.maximum(np.sqrt(np.diag(cov_w)), top_spread / 10)
    spread = np.clip(spread, STEP_FLOOR, top_spread)
    i_best = int(np.argmax(np.where(np.isfinite(lp), lp, -np.inf)))
    here, f_here = x[i_best], float(lp[i_best])
    centre, cov, step = None, None, None
    for _ in range(NEWTON_STEPS):
        f, g, hess = _stencil(problem, here, spread)
        if not (np.all(np.isfinite(g)) and np.all(np.isfinite(hess))):
            break  # a stencil point did not simulate
        if step is not None and not f >= f_here - 1e-6 * abs(f_here):
            step = step / 2  # the last step overshot: back half of it
            here = here - step
            continue
        w, v = np.linalg.eigh(-0.5 * (hess + hess.T))
        if not (np.isfinite(f) and np.all(np.isfinite(w)) and w.min() > 0):
            break
        centre, f_here = here, f
        cov = (v / w) @ v.T
        spread = np.clip(np.sqrt(np.diag(cov)), STEP_FLOOR, top_spread)
        step = cov @ g
        # no further than the flow's spread in one step (a far step is a poor quadratic)
        step = step * min(1.0, float(np.min(top_spread / (np.abs(step) + 1e-300))))
        here = here + step
    if cov is not None:
        return centre, 0.5 * (cov + cov.T) * REFINE_INFLATE**2
    return mean_w, cov_w * REFINE_INFLATE**2


def _posterior(problem, theta, logp, imp_settings: dict, imp, seed: int, elapsed: float):
    """A run-layer Posterior of the resampled flow draws (no sampler iterations), as the start
    pipeline's importance posterior is (:func:`treeinfer.inference.fast.importance_run_result`)."""
    from ..inference.fast import importance_run_result
    from ..inference.problem import Posterior
    from ..model.gains import gains_from_theta

    theta = np.asarray(theta, np.float32)
    logp = np.asarray(logp, np.float32)
    run_settings = {
        **imp_settings,
        "n_iterations": 0,
        "n_iterations_done": 0,
        "start_iteration": 0,
        "seed": seed,
    }
    run = importance_run_result(theta, logp, run_settings, imp, elapsed)
    run = run._replace(stop_reason="amortised posterior, checked: " + run.stop_reason)
    kp, kd = gains_from_theta(theta, problem.sim.n_joints)
    settings = {
        "problem": problem.settings,
        "sampler": "amortised",
        "sampler_options": {"n_draws": imp_settings["n_draws"]},
        "n_particles": len(theta),
        "n_iterations": 0,
        "seed": int(seed),
        "run": run_settings,
    }
    return Posterior(theta, np.asarray(kp), np.asarray(kd), logp, problem.labels, run, settings)


def amortised_start(
    am, force, disp, model_path: str = "", n_draws: int = DEFAULT_DRAWS, seed: int = 0
) -> tuple[Callable, dict]:
    """``(start, report)``: ``start(problem, config, log) -> posterior or None`` for
    :func:`treeinfer.runs.run_inference` (None: the checks failed and the run takes the
    simulator-based path), and the report it fills (summary.json ``amortised``): the flow's
    posterior and its latency now, the checks' outcome when the start runs.

    ``force``, ``disp`` [B, T]: the recordings (already checked against the model's layout:
    :meth:`~treeinfer.amortised.estimator.Amortised.check_recordings`)."""
    from .estimator import summarize

    # the posterior alone: features, summary, flow draws and their densities, in NumPy (no
    # program to compile: the first recording of a process costs what the next ones do)
    t0, c0 = time.perf_counter(), time.process_time()
    feats = am.features(force, disp)
    draws, log_q = am.draw_from_features(feats, n_draws, seed)
    latency = time.perf_counter() - t0
    latency_cpu = time.process_time() - c0  # CPU-s: the wall on a shared CPU is the load's
    t_answer = time.perf_counter()
    report = {
        "model": str(model_path),
        "tree_fingerprint": am.meta["tree_fingerprint"],
        "latency_ms": round(1e3 * latency, 2),
        "latency_cpu_ms": round(1e3 * latency_cpu, 2),
        "n_draws": int(n_draws),
        "flow_posterior": summarize(draws, am.labels),
        "used": False,
    }
    reasons = domain_reasons(am, feats)

    def start(problem, config, log):
        # from the flow's answer to here: the run layer built the problem (the simulator, the
        # likelihood's force-noise reference fit), which the check needs and the answer not
        report["before_check_s"] = round(time.perf_counter() - t_answer, 2)
        if reasons:
            report.update(check="domain", reason="; ".join(reasons))
            return None
        if problem.model is not None or list(problem.labels) != am.labels:
            why = (
                f"the run's parameters are {list(problem.labels)}, the model's {am.labels} "
                "(it needs --likelihood gaussian with sigma_x inferred)"
            )
            report.update(check="columns", reason=why)
            return None
        o = config["options"]
        t1 = time.perf_counter()
        imp, idx = refine(
            am, problem, feats, draws, log_q, int(o["particles"]), int(o["seed"]), log
        )
        report.update(
            check="importance",
            khat=float(imp.khat),
            ess=float(imp.ess),
            rounds=int(imp.rounds),
            n_evaluated=int(len(imp.draws)),
            check_s=round(time.perf_counter() - t1, 2),
        )
        log(
            f"amortised check: {report['check_s']:.2f} s (importance weights of "
            f"{len(imp.draws)} draws, {imp.rounds - 1} refinement round(s)), after "
            f"{report['before_check_s']:.2f} s building the run's problem (the simulator, the "
            "likelihood's force-noise reference)"
        )
        if not imp.ok:
            report["reason"] = imp.reason + (
                f" after {imp.rounds - 1} refinement round(s)" if imp.rounds > 1 else ""
            )
            return None
        bad = predictive_reasons(am, feats, imp.draws[idx, -1])
        if bad:
            report.update(check="predictive", reason="; ".join(bad))
            return None
        report["used"] = True
        settings = {
            "method": "amortised",
            "khat": float(imp.khat),
            "ess": float(imp.ess),
            "n_draws": int(len(imp.draws)),
            "rounds": int(imp.rounds),
            "lm_iterations": 0,
        }
        return _posterior(
            problem,
            imp.draws[idx],
            imp.log_density[idx],
            settings,
            imp,
            int(o["seed"]),
            latency + report["check_s"],
        )

    return start, report
