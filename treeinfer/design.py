"""Where to pull next: score candidate pulls by the expected information they bring.

Given posterior particles ``theta [P, D]`` (``log Kp``, ``log Kd`` of the inferred joints) from
the pulls made so far, and a Gaussian noise model on the recorded displacement (``sigma_x`` m,
white, on every sample), each candidate next pull ``c`` (grasp fraction on the grasped branch,
peak force, profile kind, optionally a pull direction) gets a score:

**Expected information gain (default).** ``EIG(c) = I(theta; y_c)``, the expected reduction of
the posterior entropy of theta from observing ``y_c = tau(theta, c) + eps``,
``eps ~ N(0, sigma_x^2 I_T)``. We use the Laplace / Fisher approximation

    EIG(c) ~= 0.5 * E_{theta ~ p}[ log det(I_D + Sigma F_c(theta)) ],
    F_c(theta) = J_c(theta)^T J_c(theta) / sigma_x^2,

with ``Sigma`` [D, D] the covariance of the particles and ``J_c(theta)`` [T, D] the sensitivity
of the displacement trajectory to theta, by central differences in log space (step ``h``:
``J[:, d] = (tau(theta + h e_d) - tau(theta - h e_d)) / 2h``). It is exact for a linear model
with a Gaussian prior (then F does not depend on theta and the formula is the closed form), and
the usual linearisation otherwise: it treats the posterior as Gaussian with covariance Sigma and
the simulator as linear over the posterior's width at each particle. It is not bounded by
``log P`` (as nested Monte Carlo is), so it still ranks pulls that are very informative.

Cost: ``M * 2D * C`` rollouts for ``C`` candidates and ``M`` particles (a seeded subsample of
the posterior, default 32), all in **one** jitted batched :func:`treeinfer.simulator.simulate`
call, plus ``O(M C (T D^2 + D^3))`` arithmetic. E.g. 100 candidates, 32 particles and the
2-branch example (D = 4): 25,600 rollouts, about a second on a 2-core CPU after compiling.

**Nested Monte Carlo (check).** :func:`nested_mc_eig` is the prior-contrastive estimate
``mean_n [log p(y_n | theta_n) - log mean_m p(y_n | theta_m)]`` with ``y_n`` drawn at particle
``theta_n`` and the inner average over all particles (the own one included: a lower bound that
converges to the EIG as ``P`` grows; it cannot exceed ``log P``). ``P * C`` rollouts, no
linearisation; use it to check the Laplace ranking where the EIG is well below ``log P``.

**Target (``target=``).** The expected reduction of the predictive variance of a stated future
manipulation (a :class:`Target`: the displacement trajectory at grasp fraction ``g`` under a
profile with peak force ``F``), linearised: with ``G(theta)`` [T, D] the target's sensitivity,

    before = mean_t G_t Sigma G_t^T,   after_c = mean_t G_t Sigma'_c G_t^T,
    Sigma'_c = (Sigma^-1 + F_c)^-1 = S (I + S^T F_c S)^-1 S^T   (Sigma = S S^T),

averaged over particles; the score is ``before - after_c`` (m^2, the mean over the target's
samples of the variance removed) and ``band_std_after = sqrt(after_c)`` (m) is reported beside
it (a Gaussian 95% band is ``3.92`` times as wide). Cost: ``M * 2D * (C + 1)`` rollouts.

Candidates: :func:`candidate_grid` crosses grasp fractions, peak forces, profile kinds (keys of
:data:`treeinfer.forces.SHAPES`, with the standard timing of :data:`STANDARD_TIMING`) and
directions. A direction (``[3]`` unit vector, world frame) is passed to the simulator as
``direction=`` ``[C, 3]``; today's simulator pulls along gravity only, so a direction other than
``None`` raises :class:`~treeinfer.errors.ConfigError` until it gains that argument.

Everything here is generic in the forward model: the estimators take a batched
``forward(theta [N, D]) -> (tau [N, C, T], ok [N, C])``; :func:`simulator_forward` builds it from
a :class:`~treeinfer.simulator.Simulator`.
"""

from __future__ import annotations

import inspect
import itertools
import math
import re
from collections.abc import Callable, Sequence
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .errors import ConfigError
from .forces import format_spec, from_spec
from .gradients import default_rel_step
from .likelihood import gains_from_theta

try:  # the application-layer refactor moves the simulator to treeinfer.sim
    from .sim import Simulator, simulate
except ImportError:
    from .simulator import Simulator, simulate

__all__ = [
    "STANDARD_TIMING",
    "Candidate",
    "Suggestions",
    "Target",
    "candidate_forces",
    "candidate_grid",
    "candidate_spec",
    "fd_jacobian",
    "laplace_eig",
    "nested_mc_eig",
    "nested_mc_eig_from_rollouts",
    "noise_sigma_of_run",
    "parse_target",
    "particle_covariance",
    "plot_scores",
    "score_candidates",
    "simulator_forward",
    "suggest_for_run",
    "target_variance",
]

ForwardFn = Callable[[jax.Array], tuple[jax.Array, jax.Array]]
"""``theta [N, D] -> (tau [N, C, T] m, ok [N, C] bool)``: the C candidate pulls at N points."""

# Timing of each profile kind, as fractions of the pull's duration (the middle of the ranges
# treeinfer.forces.random_specs draws from): a candidate is fixed by kind, peak and grasp alone.
STANDARD_TIMING: dict[str, dict[str, float]] = {
    "ramp": {"start": 0.05, "ramp": 0.5},
    "hold": {"start": 0.05, "ramp": 0.2, "hold": 0.2, "release": 0.15},
    "release": {"start": 0.05, "ramp": 0.3, "release": 0.2},
    "step": {"start": 0.1, "rise": 0.1},
}


# ==== candidates ==================================================================================
class Candidate(NamedTuple):
    """One candidate pull.

    grasp_fraction: where along the grasped branch (0 at its joint, 1 at its tip).
    peak_force: N, the profile's peak (downward along gravity unless ``direction`` is given).
    profile_kind: a key of :data:`treeinfer.forces.SHAPES` (timing: :data:`STANDARD_TIMING`).
    direction: None (along gravity) or a [3] unit vector in the world frame.
    """

    grasp_fraction: float
    peak_force: float
    profile_kind: str = "ramp"
    direction: tuple[float, float, float] | None = None

    def to_dict(self) -> dict:
        return {
            "grasp_fraction": float(self.grasp_fraction),
            "peak_force": float(self.peak_force),
            "profile_kind": self.profile_kind,
            "direction": None if self.direction is None else [float(v) for v in self.direction],
        }


def _check_direction(d, where: str):
    if d is None:
        return None
    try:
        v = np.asarray(d, float).reshape(3)
    except (TypeError, ValueError):
        raise ConfigError(f"{where}: a direction must be 3 numbers (x, y, z), got {d!r}") from None
    n = float(np.linalg.norm(v))
    if not np.all(np.isfinite(v)) or n == 0:
        raise ConfigError(f"{where}: a direction must be a finite non-zero vector, got {d!r}")
    return tuple(float(x) for x in v / n)


def _check_candidate(c: Candidate, where: str = "candidate") -> Candidate:
    g, f = c.grasp_fraction, c.peak_force
    if not (isinstance(g, (int, float, np.floating)) and math.isfinite(g) and 0 < g <= 1):
        raise ConfigError(f"{where}: grasp_fraction must be in (0, 1], got {g!r}")
    if not (isinstance(f, (int, float, np.floating)) and math.isfinite(f)):
        raise ConfigError(f"{where}: peak_force must be a finite number of newtons, got {f!r}")
    if c.profile_kind not in STANDARD_TIMING:
        raise ConfigError(
            f"{where}: profile_kind must be one of {sorted(STANDARD_TIMING)}, "
            f"got {c.profile_kind!r}"
        )
    return Candidate(float(g), float(f), c.profile_kind, _check_direction(c.direction, where))


def candidate_grid(
    grasp_fractions: Sequence[float],
    peak_forces: Sequence[float],
    profile_kinds: Sequence[str] = ("ramp",),
    directions: Sequence | None = None,
) -> list[Candidate]:
    """Every combination of the given grasp fractions, peak forces (N), kinds and directions
    (None: along gravity only), in that nesting order (directions innermost)."""
    dirs = [None] if directions is None or len(directions) == 0 else list(directions)
    for name, seq in (
        ("grasp_fractions", grasp_fractions),
        ("peak_forces", peak_forces),
        ("profile_kinds", profile_kinds),
    ):
        if len(seq) == 0:
            raise ConfigError(f"candidates: {name} is empty")
    return [
        _check_candidate(Candidate(float(g), float(f), k, d), f"candidate (g={g}, F={f}, {k})")
        for g, f, k, d in itertools.product(grasp_fractions, peak_forces, profile_kinds, dirs)
    ]


def candidate_spec(c: Candidate, duration: float) -> str:
    """The :mod:`treeinfer.forces` spec of a candidate's profile over ``duration`` s."""
    timing = {k: round(v * duration, 6) for k, v in STANDARD_TIMING[c.profile_kind].items()}
    return format_spec(c.profile_kind, peak=c.peak_force, **timing)


def candidate_forces(candidates: Sequence[Candidate], duration: float, dt: float) -> np.ndarray:
    """[C, T] N: the candidates' force profiles sampled every ``dt`` s."""
    return np.stack([from_spec(candidate_spec(c, duration), duration, dt) for c in candidates])


class Target(NamedTuple):
    """A future manipulation whose predictive band should shrink: the displacement trajectory
    at ``grasp_fraction`` under a ``profile_kind`` pull of ``peak_force`` N (standard timing)."""

    grasp_fraction: float
    peak_force: float
    profile_kind: str = "ramp"
    direction: tuple[float, float, float] | None = None

    def candidate(self) -> Candidate:
        return Candidate(*self)

    def describe(self) -> str:
        d = "" if self.direction is None else f" along {list(self.direction)}"
        return (
            f"displacement at grasp fraction {self.grasp_fraction:g} under a {self.profile_kind} "
            f"pull of {self.peak_force:g} N{d}"
        )


_TARGET_KEYS = {"grasp": "grasp_fraction", "peak": "peak_force", "kind": "profile_kind"}


def parse_target(text: str) -> Target:
    """``"grasp=0.5,peak=5[,kind=ramp]"`` -> :class:`Target` (grasp fraction, N, profile kind)."""
    where = f"--target {text!r}"
    fields: dict = {}
    for item in filter(None, (s.strip() for s in str(text).split(","))):
        m = re.fullmatch(r"(\w+)\s*=\s*(\S+)", item)
        if not m or m.group(1) not in _TARGET_KEYS:
            raise ConfigError(f"{where}: expected grasp=G,peak=F[,kind=K], got item {item!r}")
        key, val = _TARGET_KEYS[m.group(1)], m.group(2)
        if key != "profile_kind":
            try:
                val = float(val)
            except ValueError:
                raise ConfigError(f"{where}: {m.group(1)} must be a number, got {val!r}") from None
        fields[key] = val
    missing = [k for k, v in _TARGET_KEYS.items() if v not in fields and k != "kind"]
    if missing:
        raise ConfigError(
            f"{where}: missing {', '.join(missing)} (expected grasp=G,peak=F[,kind=K])"
        )
    c = _check_candidate(Candidate(**fields), where)
    return Target(*c)


# ==== estimators (generic in the forward model) ===================================================
def particle_covariance(theta, valid=None) -> np.ndarray:
    """[D, D] covariance (``ddof=1``) of the valid particles ``theta [P, D]``."""
    theta = np.asarray(theta, float)
    if valid is not None:
        theta = theta[np.asarray(valid, bool)]
    if theta.ndim != 2 or theta.shape[0] < 2:
        raise ConfigError(
            f"particles: need at least 2 valid particles [P, D], got shape {theta.shape}"
        )
    return np.atleast_2d(np.cov(theta, rowvar=False))


def fd_jacobian(forward: ForwardFn, theta: jax.Array, rel_step: float | None = None):
    """Central-difference sensitivities of ``forward`` at ``theta [M, D]`` (log units).

    Evaluates ``forward`` **once** on the ``M * 2D`` points ``theta_m +- h e_d`` and returns
    ``(J [M, C, T, D], ok [M, C])`` with ``J[..., d] = (tau(+h e_d) - tau(-h e_d)) / 2h``
    (the step as represented in floating point); ``ok`` is False where any of the 2D rollouts
    of that particle and candidate was unstable (J is 0 there). ``rel_step`` defaults to
    ``eps ** (1/3)`` of theta's dtype (a relative step in the gains, since theta is a log)."""
    theta = jnp.asarray(theta)
    m, d = theta.shape
    h = default_rel_step(theta.dtype) if rel_step is None else float(rel_step)
    eye = h * jnp.eye(d, dtype=theta.dtype)
    plus = theta[:, None, :] + eye[None]  # [M, D, D]
    minus = theta[:, None, :] - eye[None]
    pts = jnp.concatenate([plus, minus], axis=1).reshape(m * 2 * d, d)
    tau, ok = forward(pts)
    c, t = tau.shape[1], tau.shape[2]
    tau = tau.reshape(m, 2, d, c, t)
    ok = jnp.all(ok.reshape(m, 2, d, c), axis=(1, 2))
    two_h = jnp.diagonal(plus - minus, axis1=1, axis2=2)  # [M, D]
    jac = (tau[:, 0] - tau[:, 1]) / two_h[:, :, None, None]  # [M, D, C, T]
    jac = jnp.where(ok[:, None, :, None], jac, 0.0)
    return jnp.moveaxis(jac, 1, -1), ok


def _sqrt_cov(cov) -> jax.Array:
    """``S`` [D, D] with ``S S^T = cov`` (symmetric square root; eigenvalues clipped at 0, so a
    rank-deficient particle covariance is fine: no information is counted along its null space)."""
    lam, v = jnp.linalg.eigh(jnp.asarray(cov))
    return v * jnp.sqrt(jnp.clip(lam, 0.0, None))[None, :]


def _weighted_mean(x, ok):
    """Mean of ``x [M, C]`` over the particles with ``ok [M, C]``; NaN where none is ok."""
    okf = ok.astype(x.dtype)
    n = jnp.sum(okf, axis=0)
    return jnp.where(n > 0, jnp.sum(jnp.where(ok, x, 0.0), axis=0) / jnp.maximum(n, 1.0), jnp.nan)


def laplace_eig(jac: jax.Array, cov, sigma_x: float, ok=None) -> jax.Array:
    """``0.5 mean_m log det(I + S^T F_mc S)`` [C] nats; ``F = J^T J / sigma_x^2``, ``S S^T = cov``.

    jac: [M, C, T, D] m per log unit; cov: [D, D]; ok: [M, C] (particles left out of the mean
    where False; default all). ``det(I + Sigma F) = det(I + S^T F S)``, the symmetric form."""
    s = _sqrt_cov(cov).astype(jac.dtype)
    js = jnp.einsum("mctd,de->mcte", jac, s) / sigma_x  # whitened sensitivities
    a = jnp.einsum("mcte,mctf->mcef", js, js)
    eye = jnp.eye(a.shape[-1], dtype=a.dtype)
    _, logdet = jnp.linalg.slogdet(eye + a)
    ok = jnp.ones(logdet.shape, bool) if ok is None else jnp.asarray(ok)
    return 0.5 * _weighted_mean(logdet, ok)


def target_variance(jac: jax.Array, jac_target: jax.Array, cov, sigma_x: float, ok=None):
    """Linearised predictive variance of a target before and after each candidate.

    jac: [M, C, T, D] candidate sensitivities; jac_target: [M, T', D] the target's (m per log
    unit); cov: [D, D]; ok: [M, C]. Returns ``(before [C], after [C])`` in m^2: the mean over the
    target's T' samples of ``G_t Sigma G_t^T`` and ``G_t Sigma'_c G_t^T`` with
    ``Sigma'_c = S (I + S^T F_c S)^-1 S^T``, averaged over the ok particles."""
    s = _sqrt_cov(cov).astype(jac.dtype)
    js = jnp.einsum("mctd,de->mcte", jac, s) / sigma_x
    a = jnp.einsum("mcte,mctf->mcef", js, js)  # S^T F S
    eye = jnp.eye(a.shape[-1], dtype=a.dtype)
    gs = jnp.einsum("mtd,de->mte", jac_target, s)  # [M, T', D]
    before = jnp.mean(jnp.sum(gs**2, -1), -1)  # [M]
    # G S (I + A)^-1 S^T G^T, by a solve (I + A is SPD and well conditioned)
    gs_t = jnp.broadcast_to(
        jnp.swapaxes(gs, -1, -2)[:, None], a.shape[:3] + gs.shape[1:2]
    )  # [M, C, D, T']
    sol = jnp.linalg.solve(eye + a, gs_t)
    after = jnp.mean(jnp.einsum("mte,mcet->mct", gs, sol), -1)  # [M, C]
    ok = jnp.ones(after.shape, bool) if ok is None else jnp.asarray(ok)
    return _weighted_mean(jnp.broadcast_to(before[:, None], after.shape), ok), _weighted_mean(
        after, ok
    )


def nested_mc_eig(
    forward: ForwardFn, theta: jax.Array, sigma_x: float, key: jax.Array
) -> jax.Array:
    """Prior-contrastive nested Monte Carlo EIG [C] nats with the particles as prior samples.

    ``mean_n [log p(y_n | theta_n) - log mean_m p(y_n | theta_m)]``, ``y_n = tau(theta_n) + eps_n``;
    Gaussian constants cancel. One ``forward`` call on ``theta [P, D]`` (``P * C`` rollouts);
    particles unstable for a candidate are left out of that candidate's sums. A lower bound on
    the EIG under the particle prior that converges as ``P`` grows; never above ``log P``."""
    tau, ok = forward(jnp.asarray(theta))  # [P, C, T], [P, C]
    return nested_mc_eig_from_rollouts(tau, ok, sigma_x, key)


def nested_mc_eig_from_rollouts(
    tau: jax.Array, ok: jax.Array, sigma_x: float, key: jax.Array
) -> jax.Array:
    """:func:`nested_mc_eig` given the rollouts ``tau [P, C, T]`` m and ``ok [P, C]``."""
    eps = sigma_x * jax.random.normal(key, tau.shape, tau.dtype)
    y = tau + eps
    # squared distances ||y_n - tau_m||^2 for all n, m per candidate: [C, N, M]
    yy = jnp.sum(y**2, -1).T[:, :, None]
    tt = jnp.sum(tau**2, -1).T[:, None, :]
    yt = jnp.einsum("nct,mct->cnm", y, tau)
    d2 = jnp.maximum(yy + tt - 2 * yt, 0.0)
    log_lik = -d2 / (2 * sigma_x**2)  # [C, N, M]
    okc = ok.T  # [C, P]
    log_lik = jnp.where(okc[:, None, :], log_lik, -jnp.inf)
    n_ok = jnp.sum(okc, -1).astype(tau.dtype)
    log_marg = (
        jax.scipy.special.logsumexp(log_lik, axis=-1) - jnp.log(jnp.maximum(n_ok, 1.0))[:, None]
    )
    own = -jnp.sum(eps**2, -1).T / (2 * sigma_x**2)  # [C, N]: log p(y_n | theta_n)
    per = jnp.where(okc, own - log_marg, 0.0)
    return jnp.where(n_ok > 0, jnp.sum(per, -1) / jnp.maximum(n_ok, 1.0), jnp.nan)


# ==== the simulator as the forward model ==========================================================
def _accepts_direction() -> bool:
    return "direction" in inspect.signature(simulate).parameters


def _directions_array(candidates: Sequence[Candidate], sim: Simulator):
    if all(c.direction is None for c in candidates):
        return None
    if not _accepts_direction():
        raise ConfigError(
            "directions: this treeinfer's simulator pulls along gravity only (simulate() has no "
            "direction= argument yet); leave --directions out"
        )
    g = tuple(float(v) for v in sim.gravity_dir)
    return np.asarray([g if c.direction is None else c.direction for c in candidates], float)


def simulator_forward(sim: Simulator, forces, grasp_fraction, direction=None) -> ForwardFn:
    """``forward(theta [N, 2R]) -> (tau [N, C, T], stable [N, C])`` of the C profiles
    ``forces [C, T]`` N at ``grasp_fraction [C]`` (and ``direction [C, 3]``, passed to
    :func:`~treeinfer.simulator.simulate` as ``direction=`` when given), one batched call."""
    forces = jnp.asarray(forces)
    grasp = jnp.asarray(grasp_fraction)
    extra = {} if direction is None else {"direction": jnp.asarray(direction)}

    def forward(theta):
        kp, kd = gains_from_theta(theta, sim.n_joints)
        r = simulate(sim, kp, kd, forces, grasp, **extra)
        return r.tau, r.stable

    return forward


@partial(jax.jit, static_argnums=(0, 6))
def _laplace_scores(
    sim, theta, cov, forces, grasp, direction, rel_step, sigma_x, target, onehot=None
):
    """One compiled program: the FD sensitivities of all candidates (and the target) at all
    subsampled particles in one ``simulate`` call, and the scores. ``onehot`` [D]: score the
    variance reduction of that parameter instead (its sensitivity is the unit vector)."""
    if target is not None:  # the target rides along as one more profile of the same batch
        t_forces, t_grasp, t_dir = target
        forces = jnp.concatenate([forces, t_forces[None]], 0)
        grasp = jnp.concatenate([grasp, t_grasp[None]], 0)
        if direction is not None:
            direction = jnp.concatenate([direction, t_dir[None]], 0)
    jac, ok = fd_jacobian(simulator_forward(sim, forces, grasp, direction), theta, rel_step)
    if onehot is not None:
        g = jnp.broadcast_to(onehot.astype(jac.dtype), (jac.shape[0], 1, jac.shape[-1]))
        return jnp.stack(target_variance(jac, g, cov, sigma_x, ok)), jnp.mean(ok, 0)
    if target is None:
        return laplace_eig(jac, cov, sigma_x, ok), jnp.mean(ok, 0)
    ok_t = ok[:, -1:]
    jac_c, ok_c = jac[:, :-1], ok[:, :-1] & ok_t
    before, after = target_variance(jac_c, jac[:, -1], cov, sigma_x, ok_c)
    return jnp.stack([before, after]), jnp.mean(ok_c, 0)


@partial(jax.jit, static_argnums=0)
def _nmc_scores(sim, theta, forces, grasp, direction, sigma_x, key):
    tau, ok = simulator_forward(sim, forces, grasp, direction)(theta)
    return nested_mc_eig_from_rollouts(tau, ok, sigma_x, key), jnp.mean(ok, 0)


# ==== the ranked table ============================================================================
class Suggestions(NamedTuple):
    """Candidates ranked by score (best first).

    candidates: the C candidates, best first. score: [C] nats (objective ``"eig"``), m^2 of
    predictive variance removed (``"target"``) or log units^2 of one parameter's variance
    removed (``"parameter"``). stable_share: [C] share of the subsampled particles whose
    rollouts of that candidate were all stable. band_std_before, band_std_after: [C] the
    target's linearised predictive std (m) or the parameter's std (log units) before/after
    (None for ``"eig"``). settings: estimator, sigma_x, particle counts, rel_step, duration, dt,
    cost in rollouts, target. specs: [C] the force-profile spec of each candidate.
    """

    candidates: tuple[Candidate, ...]
    score: np.ndarray
    stable_share: np.ndarray
    band_std_before: np.ndarray | None
    band_std_after: np.ndarray | None
    specs: tuple[str, ...]
    settings: dict

    @property
    def best(self) -> Candidate:
        return self.candidates[0]

    def to_dict(self) -> dict:
        """JSON-serialisable: settings and one row per candidate (rank order)."""
        rows = []
        for i, c in enumerate(self.candidates):
            row = {
                "rank": i + 1,
                **c.to_dict(),
                "spec": self.specs[i],
                "score": _num(self.score[i]),
                "stable_share": _num(self.stable_share[i]),
            }
            if self.band_std_after is not None:
                unit = "log" if self.settings.get("objective") == "parameter" else "m"
                row[f"std_before_{unit}"] = _num(self.band_std_before[i])
                row[f"std_after_{unit}"] = _num(self.band_std_after[i])
            rows.append(row)
        return {"settings": self.settings, "candidates": rows}

    def table(self, top: int | None = None) -> str:
        """Plain-text ranked table (the ``top`` best rows; all by default)."""
        obj = self.settings.get("objective", "eig")
        tgt = obj != "eig"
        unit, after, scale = {
            "eig": ("EIG [nats]", "", 1.0),
            "target": ("var cut [mm^2]", "band std [mm]", 1e3),
            "parameter": ("var cut [log^2]", "std after", 1.0),
        }[obj]
        head = f"{'rank':>4}  {'grasp':>6}  {'peak [N]':>8}  {'kind':>7}  {'direction':>18}"
        head += f"  {unit:>15}"
        head += f"  {after:>13}" if tgt else ""
        head += f"  {'stable':>6}"
        lines = [head]
        n = len(self.candidates) if top is None else min(top, len(self.candidates))
        for i in range(n):
            c = self.candidates[i]
            d = (
                "gravity"
                if c.direction is None
                else "(" + ",".join(f"{v:.2f}" for v in c.direction) + ")"
            )
            s = self.score[i] * scale**2
            line = (
                f"{i + 1:>4}  {c.grasp_fraction:>6.3g}  {c.peak_force:>8.3g}  {c.profile_kind:>7}"
            )
            line += f"  {d:>18}  {s:>15.4g}"
            if tgt:
                line += f"  {scale * self.band_std_after[i]:>13.3g}"
            lines.append(line + f"  {self.stable_share[i]:>6.0%}")
        return "\n".join(lines)


def _num(x):
    x = float(x)
    return x if math.isfinite(x) else None


def score_candidates(
    sim: Simulator,
    theta,
    candidates: Sequence[Candidate],
    sigma_x: float,
    duration: float,
    *,
    valid=None,
    n_particles: int = 32,
    target: Target | None = None,
    parameter: str | None = None,
    estimator: str = "laplace",
    rel_step: float | None = None,
    seed: int = 0,
) -> Suggestions:
    """Rank ``candidates`` for the posterior particles ``theta [P, 2R]`` (log Kp, log Kd).

    Args:
      sim: the compiled tree (its ``obs_dt`` is the candidates' sample interval).
      candidates: from :func:`candidate_grid`.
      sigma_x: m, std of the white Gaussian noise on each displacement sample.
      duration: s, length of each candidate pull (T = duration / obs_dt samples).
      valid: [P] bool, particles to use (default: all with finite theta).
      n_particles: M, size of the seeded subsample the sensitivities are taken at (all
        particles still give the covariance); nested MC uses all valid particles.
      target: score by the reduction of this manipulation's predictive variance instead of EIG.
      parameter: score by the expected reduction of one parameter's posterior variance (log
        units^2, linearised as for ``target``): a label such as ``"Kd[branch1]"``, or
        ``"worst"`` for the parameter with the largest particle std now. ``band_std_*`` then
        hold that parameter's std before/after. No extra rollouts.
      estimator: ``"laplace"`` (default) or ``"nmc"`` (nested Monte Carlo; EIG only).
      rel_step: central-difference step in log units (default ``eps ** (1/3)``).
      seed: seeds the subsample and the nested-MC noise.

    Returns :class:`Suggestions`, best first (ties and NaN scores last).
    """
    if not (isinstance(sigma_x, (int, float)) and math.isfinite(sigma_x) and sigma_x > 0):
        raise ConfigError(f"sigma_x: must be a positive number of metres, got {sigma_x!r}")
    if estimator not in ("laplace", "nmc"):
        raise ConfigError(f"estimator: expected 'laplace' or 'nmc', got {estimator!r}")
    if estimator == "nmc" and (target is not None or parameter is not None):
        raise ConfigError(
            "estimator 'nmc' scores the EIG only; use 'laplace' with a target or parameter"
        )
    if target is not None and parameter is not None:
        raise ConfigError("give a target or a parameter to score by, not both")
    if (
        isinstance(n_particles, bool)
        or not isinstance(n_particles, (int, np.integer))
        or n_particles < 2
    ):
        raise ConfigError(f"n_particles: must be an integer >= 2, got {n_particles!r}")
    if not candidates:
        raise ConfigError("candidates: none given")
    candidates = [_check_candidate(Candidate(*c)) for c in candidates]
    theta = np.asarray(theta, np.float32)
    if theta.ndim != 2 or theta.shape[1] != 2 * sim.n_joints:
        raise ConfigError(
            f"theta: expected [P, {2 * sim.n_joints}] (log Kp, log Kd), got {theta.shape}"
        )
    ok = np.all(np.isfinite(theta), axis=1)
    if valid is not None:
        ok &= np.asarray(valid, bool)
    pts = theta[ok]
    cov = particle_covariance(pts)
    labels = [f"Kp[{n}]" for n in sim.joint_names] + [f"Kd[{n}]" for n in sim.joint_names]
    onehot = None
    if parameter is not None:
        if parameter == "worst":
            parameter = labels[int(np.argmax(np.diag(cov)))]
        if parameter not in labels:
            raise ConfigError(f"parameter: expected 'worst' or one of {labels}, got {parameter!r}")
        onehot = jnp.asarray(np.eye(len(labels))[labels.index(parameter)], sim.dtype)
    forces = candidate_forces(candidates, duration, sim.obs_dt)
    grasp = np.asarray([c.grasp_fraction for c in candidates], np.float32)
    direction = _directions_array(candidates + ([target.candidate()] if target else []), sim)
    rng = np.random.default_rng(seed)
    dtype = sim.dtype
    c_dir = None if direction is None else jnp.asarray(direction[: len(candidates)], dtype)
    if estimator == "laplace":
        m = min(int(n_particles), len(pts))
        sub = pts[np.sort(rng.choice(len(pts), m, replace=False))]
        tgt = None
        if target is not None:
            tf = candidate_forces([target.candidate()], duration, sim.obs_dt)[0]
            td = jnp.zeros(3, dtype) if direction is None else jnp.asarray(direction[-1], dtype)
            tgt = (jnp.asarray(tf, dtype), jnp.asarray(target.grasp_fraction, dtype), td)
        h = default_rel_step(dtype) if rel_step is None else float(rel_step)
        out, share = _laplace_scores(
            sim,
            jnp.asarray(sub, dtype),
            jnp.asarray(cov, dtype),
            jnp.asarray(forces, dtype),
            jnp.asarray(grasp, dtype),
            c_dir,
            h,
            float(sigma_x),
            tgt,
            onehot,
        )
        out, share = np.asarray(out, float), np.asarray(share, float)
        d = pts.shape[1]
        cost = m * 2 * d * (len(candidates) + (1 if target else 0))
        if target is None and onehot is None:
            score, before, after = out, None, None
        else:
            before, after = out
            score = before - after
            before, after = np.sqrt(np.clip(before, 0, None)), np.sqrt(np.clip(after, 0, None))
    else:
        m, h = len(pts), None
        key = jax.random.key(int(seed))
        score, share = _nmc_scores(
            sim,
            jnp.asarray(pts, dtype),
            jnp.asarray(forces, dtype),
            jnp.asarray(grasp, dtype),
            c_dir,
            float(sigma_x),
            key,
        )
        score, share = np.asarray(score, float), np.asarray(share, float)
        before = after = None
        cost = m * len(candidates)
    order = np.argsort(np.where(np.isfinite(score), -score, np.inf), kind="stable")
    objective = "eig" if target is None else "target"
    objective = "parameter" if parameter is not None else objective
    settings = {
        "objective": objective,
        "estimator": estimator,
        "score_units": {
            "eig": "nats",
            "target": "m^2 (mean predictive variance removed)",
            "parameter": "log units^2 (posterior variance removed)",
        }[objective],
        "parameter": parameter,
        "sigma_x_m": float(sigma_x),
        "n_posterior_particles": len(pts),
        "n_particles_used": int(m),
        "rel_step": h,
        "duration_s": float(duration),
        "dt_s": float(sim.obs_dt),
        "n_candidates": len(candidates),
        "cost_rollouts": int(cost),
        "seed": int(seed),
        "target": None
        if target is None
        else {
            **target.candidate().to_dict(),
            "description": target.describe(),
            "spec": candidate_spec(target.candidate(), duration),
        },
        "standard_timing": STANDARD_TIMING,
    }
    specs = [candidate_spec(c, duration) for c in candidates]
    pick = lambda a: None if a is None else np.asarray(a)[order]
    return Suggestions(
        candidates=tuple(candidates[i] for i in order),
        score=np.asarray(score)[order],
        stable_share=np.asarray(share)[order],
        band_std_before=pick(before),
        band_std_after=pick(after),
        specs=tuple(specs[i] for i in order),
        settings=settings,
    )


# ==== plot ========================================================================================
def plot_scores(suggestions: Suggestions):
    """Score over grasp fraction, one line per peak force, one panel per (kind, direction).

    Returns ``(fig, axes)``."""
    import matplotlib.pyplot as plt

    cands = suggestions.candidates
    groups = sorted({(c.profile_kind, c.direction) for c in cands}, key=str)
    fig, axes = plt.subplots(1, len(groups), figsize=(4.2 * len(groups), 3.4), squeeze=False)
    axes = axes[0]
    scale, ylabel = {
        "eig": (1.0, "expected information gain [nats]"),
        "target": (1e6, "predictive variance removed [mm$^2$]"),
        "parameter": (
            1.0,
            f"variance of {suggestions.settings.get('parameter')} removed [log$^2$]",
        ),
    }[suggestions.settings.get("objective", "eig")]
    forces = sorted({c.peak_force for c in cands})
    cmap = plt.get_cmap("viridis")
    for ax, (kind, direction) in zip(axes, groups):
        for j, f in enumerate(forces):
            rows = [
                (c.grasp_fraction, s)
                for c, s in zip(cands, suggestions.score)
                if c.profile_kind == kind and c.direction == direction and c.peak_force == f
            ]
            if not rows:
                continue
            rows.sort()
            g, s = np.asarray(rows, float).T
            ax.plot(
                g, s * scale, "o-", ms=3, color=cmap(j / max(1, len(forces) - 1)), label=f"{f:g} N"
            )
        b = suggestions.best
        if b.profile_kind == kind and b.direction == direction:
            ax.plot([b.grasp_fraction], [suggestions.score[0] * scale], "r*", ms=12, label="best")
        d = "gravity" if direction is None else str(list(direction))
        ax.set_title(f"{kind} pull, {d}")
        ax.set_xlabel("grasp fraction")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[-1].legend(fontsize=7, title="peak force", title_fontsize=7)
    fig.tight_layout()
    return fig, axes


# ==== a finished run as the starting point (the service behind `treeinfer suggest`) ============
def noise_sigma_of_run(config: dict) -> tuple[float, str]:
    """``(sigma_x m, where it came from)`` for a run's ``config.json``.

    A run that records a Gaussian noise model (``problem.sigma_x`` or ``options.sigma_x``, as
    the noise-model issue adds) gives it directly; an older run gets the displacement noise its
    Boltzmann temperature stands for, inverting :func:`treeinfer.likelihood.suggest_kT` at the
    data's length and time step (``kT = sigma sqrt(T) (1 + 1 / (sqrt 2 dt))``)."""
    for where in ("problem", "options", "noise"):
        sec = config.get(where) or {}
        for key in ("sigma_x", "sigma_displacement", "sigma_x_m"):
            if isinstance(sec.get(key), (int, float)) and sec[key] > 0:
                return float(sec[key]), f"{where}.{key}"
    p = config.get("problem") or {}
    try:
        kT, dt, t = float(p["kT"]), float(p["obs_dt"]), int(p["n_steps"])
    except (KeyError, TypeError, ValueError):
        raise ConfigError(
            "run config: no noise model and no kT/obs_dt/n_steps to derive one from; give sigma_x"
        ) from None
    return kT / (
        math.sqrt(t) * (1.0 + 1.0 / (math.sqrt(2.0) * dt))
    ), "derived from kT (suggest_kT inverted)"


def suggest_for_run(
    run_dir,
    grasp_fractions: Sequence[float] = tuple(np.round(np.linspace(0.1, 1.0, 10), 2)),
    peak_forces: Sequence[float] = (2.0, 4.0, 6.0, 8.0),
    profile_kinds: Sequence[str] = ("ramp",),
    directions: Sequence | None = None,
    target: Target | str | None = None,
    parameter: str | None = None,
    sigma_x: float | None = None,
    duration: float | None = None,
    n_particles: int = 32,
    seed: int = 0,
    out=None,
    force: bool = False,
) -> Suggestions:
    """Score candidate next pulls for the posterior of a finished run folder.

    ``sigma_x`` (m) defaults to :func:`noise_sigma_of_run`; ``duration`` (s) to the run's
    training trajectory length. With ``out``, writes ``suggestions.json`` (the ranked table,
    settings, run path) and ``suggestions.png`` (:func:`plot_scores`) there; ``force``
    overwrites existing files. Returns the :class:`Suggestions`."""
    from pathlib import Path

    from ._io import atomic_write_json
    from .runs import load_run

    run = load_run(run_dir)
    noise_from = "given"
    if sigma_x is None:
        sigma_x, noise_from = noise_sigma_of_run(run.config)
    if duration is None:
        p = run.config.get("problem", {})
        duration = float(p.get("n_steps", 0)) * run.sim.obs_dt
        if not duration > 0:
            raise ConfigError(
                f"{run_dir}: cannot tell the pull duration from the run; give duration"
            )
    if isinstance(target, str):
        target = parse_target(target)
    cands = candidate_grid(grasp_fractions, peak_forces, profile_kinds, directions)
    sugg = score_candidates(
        run.sim,
        run.theta,
        cands,
        float(sigma_x),
        float(duration),
        valid=run.stable,
        n_particles=n_particles,
        target=target,
        parameter=parameter,
        seed=seed,
    )
    sugg = sugg._replace(
        settings={
            **sugg.settings,
            "run": str(Path(run_dir).resolve()),
            "sigma_x_from": noise_from,
            "labels": list(run.labels),
        }
    )
    if out is not None:
        from .plots import save_figure

        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        for name in ("suggestions.json", "suggestions.png"):
            if (out / name).exists() and not force:
                from .errors import OutputExistsError

                raise OutputExistsError(f"{out / name}: exists; use --force to overwrite")
        atomic_write_json(out / "suggestions.json", sugg.to_dict())
        fig, _ = plot_scores(sugg)
        save_figure(fig, out / "suggestions.png")
        import matplotlib.pyplot as plt

        plt.close(fig)
    return sugg
