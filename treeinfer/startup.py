"""Cold start: shapes padded to a few buckets, so a new data set reuses compiled programs.

XLA compiles one program per array shape. A robot that records 3 pulls of 300 steps today and 4
pulls of 287 steps tomorrow would compile the whole finite-difference simulator again (tens of
seconds on a small CPU), even with the persistent compilation cache on, because the cache is
keyed by shape. Padding the observations to a few bucket sizes makes both data sets one shape:

* trajectories: the next of ``2^k * {1, 1.5}`` (1, 2, 3, 4, 6, 8, 12, ...: at most 50% extra
  rows, 3 stays 3; a padded row is simulated like a real one, so on a CPU it costs its share);
* time steps: the next of ``2^k * {1, 1.25, 1.5, 1.75}`` (at most 25% extra steps to simulate,
  four buckets per doubling), at least :data:`MIN_STEPS`.

Padded entries carry ``mask = False``, which every likelihood already honours (a shorter pull
stacked with a longer one is padded the same way by
:func:`treeinfer.trajectories.stack_trajectories`), so the log density is unchanged
(``tests/test_startup.py`` checks it for the Boltzmann and Gaussian likelihoods). Particles are
*not* padded: SVGD particles interact through the kernel, so a padded particle would change the
result; use a few particle counts (64, 128, 256) instead.

Wiring: the run layer records the bucket of an ``--init importance`` run
(:func:`treeinfer.runs.problem.shape_bucket_for`, ``shape_bucket`` in config.json's problem
settings) and :class:`treeinfer.fast_posterior.BatchEvaluator` pads the data to it; its rollout
program takes the data as arguments, so it is shared by every data set of the bucket (the
samplers' programs embed the data as constants, where padding would reuse nothing). The
accuracy-controlled step is chosen on the unpadded forces.
"""

from __future__ import annotations

import math

import numpy as np

from .errors import ConfigError
from .trajectories import Observations

__all__ = ["MIN_STEPS", "bucket_observations", "steps_bucket", "trajectories_bucket"]

MIN_STEPS = 64


def _count(n, what: str) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ConfigError(f"{what}: must be an integer >= 1, got {n!r}")
    return int(n)


def trajectories_bucket(n: int) -> int:
    """The bucket of ``n`` trajectories: the smallest ``2^k`` or ``3 * 2^k`` that is >= ``n``."""
    n = _count(n, "number of trajectories")
    two = 1 << (n - 1).bit_length()
    return 3 * two // 4 if two >= 4 and 3 * two // 4 >= n else two


def steps_bucket(n: int) -> int:
    """The bucket of ``n`` time steps: the smallest ``2^k * m`` (m in 1, 1.25, 1.5, 1.75) that
    is at least ``n`` and :data:`MIN_STEPS`."""
    n = max(_count(n, "number of time steps"), MIN_STEPS)
    k = max(int(math.floor(math.log2(n))) - 2, 0)  # 2^k * {4, 5, 6, 7} spans [2^(k+2), 2^(k+3))
    while True:
        for m in (4, 5, 6, 7, 8):
            if m * (1 << k) >= n:
                return m * (1 << k)
        k += 1


def bucket_observations(
    obs: Observations, n_trajectories: int | None = None, n_steps: int | None = None
) -> Observations:
    """``obs [B, T]`` padded to ``[n_trajectories, n_steps]`` (default: the buckets of B, T).

    Padded steps hold each row's last force and displacement with velocity 0; padded rows are
    at rest (force, displacement and velocity 0); every padded entry has ``mask = False``.
    """
    b, t = np.shape(obs.force)
    nb = trajectories_bucket(b) if n_trajectories is None else _count(n_trajectories, "rows")
    nt = steps_bucket(t) if n_steps is None else _count(n_steps, "steps")
    if nb < b or nt < t:
        raise ConfigError(f"bucket_observations: [{nb}, {nt}] is smaller than the data [{b}, {t}]")

    def pad(x, hold: bool, dtype=float):
        x = np.asarray(x, dtype)
        out = np.zeros((nb, nt), dtype)
        out[:b, :t] = x
        if hold and nt > t:
            out[:b, t:] = x[:, -1:]
        return out

    return Observations(
        force=pad(obs.force, True),
        displacement=pad(obs.displacement, True),
        velocity=pad(obs.velocity, False),
        mask=pad(obs.mask, False, bool),
        dt=obs.dt,
    )
