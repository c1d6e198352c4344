"""What one tree SBC study depends on (:class:`SBCConfig`) and its prior draws."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from .stats import sample_smoothed_box

SBC_SAMPLERS = ("smc", "mh", "svgd")
SBC_LIKELIHOODS = ("gaussian", "student_t")


@dataclass
class SBCConfig:
    """Everything one tree SBC study depends on (recorded in ``config.json``).

    likelihood: ``gaussian`` or ``student_t`` (data simulated AND inferred with it).
    noise_displacement: m, fixed sigma_x (given to inference); None: sigma_x inferred with prior
      ``log sigma_x ~ Normal(log noise_prior_center, sigma_prior_scale)`` and truths drawn from it.
    n_traj, duration, dt: pulls per data set (force profiles ``forces.profile_set("mixed")``,
      drawn afresh per data set), s, s.
    sampler: ``smc`` (default), ``mh`` or ``svgd`` (:mod:`treeinfer.calibration` says which
      does what). particles: L posterior draws ranked per data set.
    smc_particles, smc_levels, smc_mutations, smc_final, smc_target_ess: the SMC cloud size N
      (>= particles; L of the N final particles are ranked), temperature levels, random-walk MH
      steps per level, MH steps at beta = 1 after the ladder, ESS share kept per level (smc).
    iterations: Adam ascent (mh) or SVGD (svgd) iterations; mh_warmup, mh_steps: MH warm-up
      and sampling steps per chain (mh).
    chunk: data sets per jitted program call.
    noise_force: relative force noise (share of the data set's peak |force|) on the RECORDED
      forces that drive inference (training and test). Not in the inference model (the noise
      engineer's decision: absorbed by sigma_x), so SBC is exact only at 0; > 0 is a
      misspecification check (ranks of the gains then show its effect).
    test_traj: unseen test pulls per data set (fresh profiles, same noise); > 0 adds the share
      of noisy test points inside the 95% predictive band (simulation + fitted noise,
      :func:`treeinfer.evaluation.metrics.noisy_predictive_interval`) and the parameter band.
    """

    datasets: int = 20
    likelihood: str = "gaussian"
    noise_displacement: float | None = None
    noise_prior_center: float = 0.002
    sigma_prior_scale: float = 0.5
    student_t_df: float = 4.0
    sampler: str = "smc"
    particles: int = 32
    smc_particles: int = 256
    smc_levels: int = 48
    smc_mutations: int = 5
    smc_final: int = 20
    smc_target_ess: float = 0.5
    iterations: int = 200
    learning_rate: float = 0.1
    mh_warmup: int = 400
    mh_steps: int = 400
    n_traj: int = 5
    duration: float = 3.0
    dt: float = 0.01
    seed: int = 0
    max_sim_dt: float | None = None
    prior_sigma: float = 0.1
    chunk: int = 8
    rel_step: float | None = None
    backend: str = "auto"
    noise_force: float = 0.0
    test_traj: int = 0

    def check(self) -> SBCConfig:
        from ..inference.problem import check_count
        from ..model.noise import check_df, check_sigma

        check_count(self.datasets, "datasets", 2)
        check_count(self.particles, "particles", 2)
        check_count(self.iterations, "iterations", 1)
        check_count(self.mh_steps, "mh_steps", 1)
        check_count(self.mh_warmup, "mh_warmup", 0)
        check_count(self.smc_levels, "smc_levels", 1)
        check_count(self.smc_mutations, "smc_mutations", 1)
        check_count(self.smc_final, "smc_final", 0)
        check_count(self.smc_particles, "smc_particles", 2)
        if self.sampler == "smc" and self.smc_particles < self.particles:
            raise ConfigError(
                f"smc_particles: the SMC cloud ({self.smc_particles}) must hold at least the "
                f"{self.particles} ranked draws (particles)"
            )
        t = self.smc_target_ess
        if not (isinstance(t, (int, float)) and 0.0 < t < 1.0):
            raise ConfigError(f"smc_target_ess: must lie in (0, 1), got {t!r}")
        check_count(self.n_traj, "n_traj", 1)
        check_count(self.chunk, "chunk", 1)
        check_count(self.test_traj, "test_traj", 0)
        if not (isinstance(self.noise_force, (int, float)) and 0.0 <= self.noise_force < 1.0):
            raise ConfigError(f"noise_force: must be a share in [0, 1), got {self.noise_force!r}")
        if self.likelihood not in SBC_LIKELIHOODS:
            raise ConfigError(
                f"likelihood: calibrate supports {', '.join(SBC_LIKELIHOODS)} (a generative noise "
                f"model to simulate from), got {self.likelihood!r}"
            )
        if self.sampler not in SBC_SAMPLERS:
            raise ConfigError(
                f"sampler: calibrate supports {', '.join(SBC_SAMPLERS)}, got {self.sampler!r}"
            )
        if self.noise_displacement is not None:
            check_sigma(self.noise_displacement, "noise_displacement")
        check_sigma(self.noise_prior_center, "noise_prior_center")
        for name in ("sigma_prior_scale", "learning_rate", "duration", "dt", "prior_sigma"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ConfigError(f"{name}: must be a finite positive number, got {v!r}")
        if self.likelihood == "student_t":
            check_df(self.student_t_df)
        if self.duration < 5 * self.dt:
            raise ConfigError(f"duration: {self.duration} s is shorter than 5 samples of dt")
        return self


def _labels(tree, infer_sigma: bool) -> tuple[str, ...]:
    return tuple(tree.parameter_labels()) + (("sigma_x",) if infer_sigma else ())


def draw_truths(tree, config: SBCConfig, rng: np.random.Generator, n: int) -> np.ndarray:
    """``[n, D]`` prior draws in theta units: log gains from the smoothed box, then
    ``log sigma_x`` from its Normal prior when sigma_x is inferred."""
    lo, hi = np.log(tree.bounds_array()[0]), np.log(tree.bounds_array()[1])
    gains = sample_smoothed_box(rng, lo, hi, config.prior_sigma * (hi - lo), n)
    if config.noise_displacement is not None:
        return gains
    ls = rng.normal(math.log(config.noise_prior_center), config.sigma_prior_scale, size=(n, 1))
    return np.concatenate([gains, ls], axis=1)
