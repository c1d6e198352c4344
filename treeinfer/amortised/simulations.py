"""Training simulations of an amortised posterior: parameter sets drawn from treeinfer's prior
(the smoothed box over the log gains, :func:`treeinfer.model.prior_terms.box_prior`, sampled
exactly, times the run's learned inequality prior on a tree with parent-child pairs, by
rejection) and the noise model (``log sigma_x`` log-uniform in its range; the recorded force
noise-free in a share of the data sets, else log-uniform in its range),
pulls drawn from the layout's profile family (:func:`treeinfer.data.forces.random_specs`), one
batched rollout per chunk of parameter sets (:func:`treeinfer.sim.simulate`, vmapped over the
pulls and, each parameter set with pulls of its own, over the sets), and the recordings'
summary features (:func:`features`) kept instead of the traces (20 000 data sets of 8 pulls x
300 samples would be 380 MB; their features 65 MB)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..data.forces import from_spec, random_specs
from ..errors import ConfigError
from ..model.prior_terms import DEFAULT_PRIOR_SIGMA
from .config import PullLayout, TrainConfig

# MAD -> standard deviation of a normal; second differences of white noise have variance 6 s^2
_MAD = 1.4826
_SECOND_DIFF = math.sqrt(6.0)
# The noise estimates' floor, a share of the feature's scale (0.8 mN of an 8 N force scale):
# a clean force's estimate is rounding (1e-7 of float32 in training, 1e-6 of a CSV's digits),
# which without a floor would be two different summaries of the same noise-free recording.
NOISE_FLOOR = 1e-4


class TrainingSet(NamedTuple):
    """theta [N, D] (log Kp, log Kd of the inferred joints, log sigma_x), feats [N, B, F] (the
    recordings' :func:`features`), and what was dropped: ``n_unstable`` parameter sets whose
    rollout was unstable (the prior restricted to stable sets, as the simulator-based posterior
    is, where unstable particles are dropped)."""

    theta: np.ndarray
    feats: np.ndarray
    n_unstable: int


def theta_box(tree, train: TrainConfig, prior_sigma: float = DEFAULT_PRIOR_SIGMA):
    """``(lower [D], upper [D], tail [D])`` of the training prior in theta units: the tree's log
    prior box with the smoothed box's Gaussian tails (``prior_sigma`` of each width), then
    ``log sigma_x`` in ``train.sigma_x_range`` (no tail)."""
    lo, hi = tree.bounds_array()
    llo, lhi = np.log(lo), np.log(hi)
    slo, shi = np.log(train.sigma_x_range[0]), np.log(train.sigma_x_range[1])
    if shi <= slo:  # a fixed noise: a sliver of width, so that the standardisation is defined
        slo, shi = slo - 1e-3, shi + 1e-3
    lower, upper = np.append(llo, slo), np.append(lhi, shi)
    tail = np.append(prior_sigma * (lhi - llo), 0.0)
    return lower, upper, tail


def draw_prior(rng: np.random.Generator, lower, upper, tail, n: int) -> np.ndarray:
    """[n, D] draws of the smoothed box: per coordinate a uniform on [lower, upper] with weight
    ``upper - lower`` and a half-normal tail of std ``tail`` on each side with weight ``sqrt(2 pi)
    tail / 2`` (:func:`treeinfer.model.priors.smoothed_box`, normalised, is this mixture)."""
    lower, upper, tail = (np.asarray(a, float) for a in (lower, upper, tail))
    width = upper - lower
    w_tail = math.sqrt(2 * math.pi) * tail / 2
    p_in = width / (width + 2 * w_tail)
    u = rng.uniform(size=(n, lower.size))
    inside = rng.uniform(lower, upper, size=(n, lower.size))
    excess = np.abs(rng.normal(size=(n, lower.size))) * tail
    below = u < (1 - p_in) / 2
    above = u > (1 + p_in) / 2
    return np.where(below, lower - excess, np.where(above, upper + excess, inside))


def inequality_log_prior(tree):
    """The run's learned inequality prior (``[n, 2R] -> [n]`` log density of the log gains;
    :func:`treeinfer.model.prior_terms.nn_inequality_prior` with the run's defaults, from the
    same disk cache), or None for a tree without parent-child pairs. The simulator-based
    posterior that checks the flow has it (``make_problem``'s ``nn_prior=True``): a flow
    trained without it spends its mass where the run's prior has little, which costs the
    importance check effective sample size on every recording of a multi-joint tree."""
    from ..model.prior_terms import nn_inequality_prior

    return nn_inequality_prior(tree) if tree.inferred_pairs() else None


def draw_training_prior(rng: np.random.Generator, tree, train: TrainConfig, n: int, ineq=None):
    """[n, D] draws of the training prior: the smoothed box (:func:`draw_prior`) times
    ``ineq`` (:func:`inequality_log_prior`; None: none) by rejection, a draw kept with
    probability ``min(1, exp(log ineq))``: the learned penalty is <= 0 up to the network's
    error, so the cap changes the prior only where that error is positive."""
    lower, upper, tail = theta_box(tree, train)
    if ineq is None:
        return draw_prior(rng, lower, upper, tail, n)
    import jax.numpy as jnp

    g = 2 * tree.n_inferred
    kept, have = [], 0
    for _ in range(1000):  # an acceptance of 1/1000 would be a broken prior, not a slow one
        theta = draw_prior(rng, lower, upper, tail, max(2 * n, 256))
        log_a = np.asarray(ineq(jnp.asarray(theta[:, :g], jnp.float32)), float)
        theta = theta[np.log(rng.uniform(size=len(theta))) < np.minimum(log_a, 0.0)]
        kept.append(theta)
        have += len(theta)
        if have >= n:
            return np.concatenate(kept)[:n]
    raise ConfigError(
        "amortise: the learned inequality prior rejected almost every draw of the tree's prior "
        "box; check the box of the parent and child joints"
    )


def draw_profiles(rng: np.random.Generator, layout: PullLayout, n: int) -> np.ndarray:
    """[n, T] N: ``n`` pulls of the layout's profile family (seeded specs, as `simulate`)."""
    specs = random_specs(layout.profile_kind, n, layout.duration, layout.peak_range, seed=rng)
    return np.stack([from_spec(s, layout.duration, layout.dt) for s in specs])


def bin_matrix(n_steps: int, bins: int) -> np.ndarray:
    """[T, bins]: the mean over each of ``bins`` consecutive equal shares of the T samples
    (``x @ W``). Bin means, not point samples: they keep what the noise averages out to."""
    idx = np.minimum((np.arange(n_steps) * bins) // n_steps, bins - 1)
    w = np.zeros((n_steps, bins))
    w[np.arange(n_steps), idx] = 1.0
    return w / w.sum(axis=0, keepdims=True)


def _noise_scale(x, xp=jnp):
    """Robust noise std along the last axis: MAD of second differences / sqrt(6) (as
    :func:`treeinfer.model.noise.estimate_displacement_noise`, in jnp over a batch)."""
    d2 = x[..., 2:] - 2 * x[..., 1:-1] + x[..., :-2]
    med = xp.median(d2, axis=-1, keepdims=True)
    return _MAD * xp.median(xp.abs(d2 - med), axis=-1) / _SECOND_DIFF


N_DYNAMICS = 6  # the hand-made summaries of summary "dynamics" (:func:`dynamics_features`)


def n_features(bins: int, summary: str) -> int:
    """The features' number per pull of a summary kind (TrainConfig.summary)."""
    return 2 * bins + 4 + (N_DYNAMICS if summary == "dynamics" else 0)


def dynamics_features(fb, xb, xp=jnp):
    """[..., B, N_DYNAMICS] per pull, from its bin means (``fb``, ``xb`` [..., B, bins], scaled):
    what sets the stiffness and the damping, summarised by hand so that the network need not
    find it in the shapes (session 13: the deep-sets summary of the shapes alone gave flows
    5-50 times wider than the simulator-based posterior in Kp and Kd):

    - the log least-squares compliance ``sum f x / sum f^2`` over the pull, and over its hold
      (the bins where |f| >= 0.9 of its largest): the static compliance, the stiffness's
      direct measure;
    - after the release (the bins after the last one with |f| >= half its largest; none for a
      ramp that never lets go): the log rms of the displacement against its value at the
      release (the ringing's size: the damping's), the log ratio of the rms of the window's
      second half to its first (the decay), and the share of bins where the displacement
      changes sign (the ringing's frequency); zeros without a release window, whose flag is
      the last feature."""
    tiny = 1e-6
    fa = xp.abs(fb)
    peak = xp.max(fa, axis=-1, keepdims=True) + tiny
    comp = xp.sum(fb * xb, axis=-1) / (xp.sum(fb * fb, axis=-1) + tiny)
    hold = fa >= 0.9 * peak
    comp_hold = xp.sum(xp.where(hold, fb * xb, 0), axis=-1) / (
        xp.sum(xp.where(hold, fb * fb, 0), axis=-1) + tiny
    )
    n = fb.shape[-1]
    idx = xp.arange(n)
    loaded = fa >= 0.5 * peak
    last = n - 1 - xp.argmax(xp.flip(loaded, axis=-1), axis=-1)  # the last loaded bin
    after = idx > last[..., None]
    n_after = xp.sum(after, axis=-1)
    mid = last[..., None] + (n_after[..., None] + 1) // 2
    first_half = after & (idx <= mid)
    second_half = after & (idx > mid)
    x_rel = xp.take_along_axis(xb, last[..., None], axis=-1)

    def rms(m):
        return xp.sqrt(xp.sum(xp.where(m, xb * xb, 0), axis=-1) / xp.maximum(xp.sum(m, -1), 1))

    has = n_after >= 4
    ring = xp.log(rms(after) / (xp.abs(x_rel[..., 0]) + tiny) + tiny)
    decay = xp.log((rms(second_half) + tiny) / (rms(first_half) + tiny))
    sign_change = (xb[..., 1:] * xb[..., :-1] < 0) & after[..., 1:]
    crossings = xp.sum(sign_change, axis=-1) / xp.maximum(n_after, 1)
    zero = xp.zeros_like(ring)
    return xp.stack(
        [
            xp.log(xp.abs(comp) + tiny),
            xp.log(xp.abs(comp_hold) + tiny),
            xp.where(has, ring, zero),
            xp.where(has, decay, zero),
            xp.where(has, crossings, zero),
            has.astype(ring.dtype),
        ],
        axis=-1,
    )


def features(
    force, disp, bins_w, force_scale: float, disp_scale: float, xp=jnp, summary: str = "shapes"
):
    """[..., B, F]: per pull the shapes of force and displacement (bin means divided by
    the pull's largest |value|), then the logs of their amplitudes (largest |bin mean| over
    ``force_scale`` / ``disp_scale``) and of their robust noise estimates. Shapes and log
    amplitudes rather than raw traces: the displacement spans the prior's hundredfold range of
    stiffness, and its amplitude against the force's is what sets the stiffness; the bin means
    hide the noise, which sets the posterior's width. ``force``, ``disp`` [..., B, T].
    ``xp``: jax.numpy (training, jitted) or numpy (a new recording's posterior,
    :mod:`treeinfer.amortised.fastpath`: no program to compile)."""
    w = xp.asarray(bins_w, force.dtype)
    tiny = 1e-6
    out = []
    for x, scale in ((force, force_scale), (disp, disp_scale)):
        b = (x / scale) @ w
        amp = xp.max(xp.abs(b), axis=-1, keepdims=True) + tiny
        out.append((b / amp, xp.log(amp)))
    (fs, fa), (xs, xa) = out
    sf = xp.log(_noise_scale(force / force_scale, xp) + NOISE_FLOOR)[..., None]
    sx = xp.log(_noise_scale(disp / disp_scale, xp) + NOISE_FLOOR)[..., None]
    extra = []
    if summary == "dynamics":  # before the four summaries the domain check reads from the end
        extra = [dynamics_features((force / force_scale) @ w, (disp / disp_scale) @ w, xp)]
    return xp.concatenate([fs, xs, *extra, fa, xa, sf, sx], axis=-1)


def training_simulator(tree, layout: PullLayout, backend: str = "auto", seed: int = 0):
    """The simulator of every training chunk: its step chosen for accuracy on pulls of the
    family at the top of the peak range (the hardest), so one compiled rollout serves all."""
    from ..sim import make_simulator

    rng = np.random.default_rng(seed)
    bank = draw_profiles(rng, layout, max(layout.n_pulls, 4))
    bank = bank / np.maximum(np.abs(bank).max(axis=1, keepdims=True), 1e-12)
    return make_simulator(
        tree,
        obs_dt=layout.dt,
        backend=backend,
        forces=bank * layout.peak_range[1],
        grasp_fraction=layout.grasp_fraction,
    )


def _rollout(sim, layout: PullLayout):
    from ..model.gains import gains_from_theta
    from ..sim import simulate

    def one(theta, forces):  # one parameter set under its own pulls [B, T]
        kp, kd = gains_from_theta(theta[None], sim.n_joints)
        r = simulate(sim, kp, kd, forces, layout.grasp_fraction)
        return r.tau[0], jnp.all(r.stable[0])

    # every data set its own pulls: with pulls shared by a chunk, the network saw as few
    # distinct pull sets as chunks and over-fitted them (coverage 0.2-0.7 at 95%)
    run = jax.jit(jax.vmap(one))

    return run


def simulate_training_set(
    tree,
    layout: PullLayout,
    train: TrainConfig,
    n: int | None = None,
    seed: int | None = None,
    sim=None,
    scales: tuple[float, float] | None = None,
    log: Callable[[str], None] = lambda m: None,
) -> tuple[TrainingSet, tuple[float, float]]:
    """``(TrainingSet, (force_scale, disp_scale))`` of ``n`` (default ``train.simulations``)
    data sets: per chunk of ``train.chunk`` parameter sets, each with its own draw of the
    layout's pulls, one batched rollout; noise added per data set.
    ``scales``: the features' normalisation (a model's own, for held-out sets); None: the force
    scale is the top of the peak range and the displacement scale the 95th percentile of the
    first chunk's largest |displacement|."""
    n = train.simulations if n is None else int(n)
    seed = train.seed if seed is None else int(seed)
    sim = training_simulator(tree, layout, train.backend, seed) if sim is None else sim
    run = _rollout(sim, layout)
    ineq = inequality_log_prior(tree)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0xA3]))
    bins_w = bin_matrix(layout.n_steps, layout.bins)
    feat_fn = jax.jit(features, static_argnums=(3, 4), static_argnames=("xp", "summary"))
    g = 2 * tree.n_inferred
    thetas, feats, unstable = [], [], 0
    done = 0
    while done < n:
        m = min(train.chunk, n - done)
        theta = draw_training_prior(rng, tree, train, train.chunk, ineq)  # one shape: one compile
        forces = draw_profiles(rng, layout, train.chunk * layout.n_pulls)
        forces = forces.reshape(train.chunk, layout.n_pulls, -1)
        tau, ok = run(jnp.asarray(theta[:, :g], jnp.float32), jnp.asarray(forces, jnp.float32))
        forces = forces[:m]
        tau, ok = np.asarray(tau, float)[:m], np.asarray(ok)[:m]
        theta = theta[:m]
        if scales is None:
            top = np.abs(tau[ok]).max(axis=(1, 2)) if ok.any() else np.ones(1)
            scales = (float(layout.peak_range[1]), float(max(np.percentile(top, 95), 1e-6)))
        sx = np.exp(theta[:, g])[:, None, None]
        sf = np.exp(rng.uniform(*np.log(train.sigma_f_range), size=(m, 1, 1)))
        sf = np.where(rng.uniform(size=(m, 1, 1)) < train.clean_force_share, 0.0, sf)
        disp = tau + sx * rng.normal(size=tau.shape)
        rec_f = forces + sf * rng.normal(size=tau.shape)
        f = feat_fn(
            jnp.asarray(rec_f, jnp.float32),
            jnp.asarray(disp, jnp.float32),
            bins_w,
            *scales,
            summary=train.summary,
        )
        thetas.append(theta[ok])
        feats.append(np.asarray(f)[ok])
        unstable += int((~ok).sum())
        done += m
        log(f"simulated {done}/{n} data sets ({unstable} unstable, dropped)")
    out = TrainingSet(
        np.concatenate(thetas).astype(np.float32),
        np.concatenate(feats).astype(np.float32),
        unstable,
    )
    return out, scales


def simulate_recordings(tree, layout: PullLayout, train: TrainConfig, n: int, seed: int, sim=None):
    """``[(theta [D], force_noise N, [Trajectory] x n_pulls)]``: ``n`` recordings drawn as the
    training sets are (the training prior, the layout's pulls, ``sigma_x`` from its range, the
    force clean in ``train.clean_force_share`` of them, else noisy in its range) on ``sim``
    (None: :func:`training_simulator`), as the files `treeinfer simulate` writes would hold
    them (unstable draws skipped): the in-distribution recordings of the check's tests, the
    experiment and the latency benchmark."""
    from ..data.trajectories import Trajectory
    from ..model.gains import gains_from_theta
    from ..sim import simulate

    sim = training_simulator(tree, layout, train.backend, seed) if sim is None else sim
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x5E]))
    theta = draw_training_prior(rng, tree, train, n, inequality_log_prior(tree))
    g = 2 * tree.n_inferred
    t = np.arange(layout.n_steps) * layout.dt
    out = []
    for i in range(n):
        forces = draw_profiles(rng, layout, layout.n_pulls)
        kp, kd = gains_from_theta(jnp.asarray(theta[i : i + 1, :g], jnp.float32), tree.n_inferred)
        r = simulate(sim, kp, kd, jnp.asarray(forces, jnp.float32), layout.grasp_fraction)
        if not bool(np.all(np.asarray(r.stable))):
            continue
        tau = np.asarray(r.tau[0], float)
        sx = float(np.exp(theta[i, g]))
        sf = float(np.exp(rng.uniform(*np.log(train.sigma_f_range))))
        sf = 0.0 if rng.uniform() < train.clean_force_share else sf
        trajs = [
            Trajectory(
                t,
                f + sf * rng.normal(size=f.shape),
                x + sx * rng.normal(size=x.shape),
                None,
                f"pull{b}",
            )
            for b, (f, x) in enumerate(zip(forces, tau))
        ]
        out.append((theta[i], sf, trajs))
    return out
