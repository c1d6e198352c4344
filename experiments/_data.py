"""Synthetic data of the sim-to-sim studies (split from :mod:`experiments.common`)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as `python experiments/<study>.py` from anywhere
    sys.path.insert(0, str(ROOT))

from experiments._config import StudyConfig, tree_path  # noqa: E402
from treeinfer.errors import SimulationError


# ==== synthetic data ==============================================================================
class SyntheticData(NamedTuple):
    """A sim-to-sim data set.

    tree, sim: the tree (grasp at the training location) and its MJX simulator.
    kp, kd: [R] true gains (N m/rad, N m s/rad); theta: [2R] their natural logs.
    train, test: lists of :class:`~treeinfer.data.trajectories.Trajectory` (s, N, m, m/s).
    test_grasp: [n_test] fraction of the branch length where each test trajectory was recorded.
    train_specs, test_specs: the force profile specs (replayable with ``forces.from_spec``).
    """

    tree: Any
    sim: Any
    kp: np.ndarray
    kd: np.ndarray
    theta: np.ndarray
    train: list
    test: list
    test_grasp: np.ndarray
    train_specs: list
    test_specs: list

    def true_params(self) -> dict:
        from treeinfer.data.trajectories import true_params_record

        return true_params_record(self.tree, self.kp, self.kd, "experiments (default_true_params)")


def _simulator(path: str, dt: float, sims=None):
    """The tree and its simulator from ``sims`` (a :class:`treeinfer.runs.SimulatorCache`, one
    per study: jitted predictions are cached on the simulator's identity)."""
    from treeinfer.runs import SimulatorCache
    from treeinfer.tree import load_tree

    tree = load_tree(path)
    return tree, (SimulatorCache() if sims is None else sims).get(tree, dt)


def seed_streams(seed: int) -> dict[str, np.random.Generator]:
    """Independent generators of one seed: true parameters, training and test profiles."""
    names = ("params", "train", "test")
    return {
        n: np.random.default_rng(s)
        for n, s in zip(names, np.random.SeedSequence(int(seed)).spawn(len(names)))
    }


def reference_trajectory(
    sim, kp, kd, force: np.ndarray, dt: float, source: str, grasp_fraction=None
):
    """Ground truth of one pull from plain MuJoCo (float64), as a Trajectory."""
    from treeinfer.data.trajectories import Trajectory, validate_trajectory
    from treeinfer.sim.reference import simulate_reference

    tau, tau_dot = simulate_reference(sim, kp, kd, force, grasp_fraction)
    if not (np.all(np.isfinite(tau)) and np.max(np.abs(tau)) < sim.max_displacement):
        raise SimulationError(
            f"{source}: the ground-truth simulation blew up; lower the peak forces"
        )
    t = np.arange(len(force), dtype=float) * dt
    return validate_trajectory(Trajectory(t, np.asarray(force, float), tau, tau_dot, source))


def make_data(cfg: StudyConfig, seed: int, sims=None) -> SyntheticData:
    """Ground truth, training set and unseen test set of ``cfg`` (see the module docstring).

    The grasp study's test set is its first ``n_test_per_location`` test profiles pulled at each
    of ``cfg.grasp_locations``; every other study's is ``n_test`` profiles at the tree's grasp."""
    from treeinfer.data import from_spec, random_specs
    from treeinfer.sim.synthetic import default_true_params

    tree, sim = _simulator(str(tree_path(cfg.tree)), float(cfg.dt), sims)
    rng = seed_streams(seed)
    kp, kd = default_true_params(tree, rng["params"])
    train_specs = random_specs(
        cfg.profile_kind, cfg.n_train, cfg.duration, cfg.peak_range, rng["train"]
    )
    test_specs = random_specs(
        cfg.profile_kind, cfg.n_test, cfg.duration, cfg.peak_range, rng["test"]
    )
    train = [
        reference_trajectory(
            sim, kp, kd, from_spec(s, cfg.duration, cfg.dt), cfg.dt, f"train_{i:03d}"
        )
        for i, s in enumerate(train_specs)
    ]
    if cfg.grasp_locations:
        specs = test_specs[: cfg.n_test_per_location]
        grasp = np.repeat(np.asarray(cfg.grasp_locations, float), len(specs))
        specs = specs * len(cfg.grasp_locations)
        test_specs = specs
    else:
        grasp = np.full(len(test_specs), tree.grasp_fraction)
    test = [
        reference_trajectory(
            sim, kp, kd, from_spec(s, cfg.duration, cfg.dt), cfg.dt, f"test_{i:03d}", float(g)
        )
        for i, (s, g) in enumerate(zip(test_specs, grasp))
    ]
    theta = np.log(np.concatenate([kp, kd]))
    return SyntheticData(tree, sim, kp, kd, theta, train, test, grasp, train_specs, test_specs)


def noise_sigmas(data: SyntheticData, level: float) -> tuple[float, float]:
    """(sigma_force N, sigma_displacement m) of relative noise ``level``: ``level`` times the
    largest absolute force / displacement over the clean training and test trajectories."""
    trajs = data.train + data.test
    f_peak = max(float(np.max(np.abs(t.force))) for t in trajs)
    x_peak = max(float(np.max(np.abs(t.displacement))) for t in trajs)
    return level * f_peak, level * x_peak


def add_relative_noise(data: SyntheticData, level: float, seed: int) -> tuple[SyntheticData, dict]:
    """``data`` with white Gaussian noise on force and displacement of every training and test
    trajectory (:func:`treeinfer.data.add_noise`, velocities then differentiated from the
    noisy displacement, as for a recording). The generator is seeded by ``(seed, level)``, so a
    level's noise does not depend on which other levels are run."""
    from treeinfer.data import add_noise

    sf, sx = noise_sigmas(data, level)
    info = {"level": level, "sigma_force_N": sf, "sigma_displacement_m": sx}
    if level == 0:
        return data, info
    rng = np.random.default_rng([int(seed), 0x5EED, round(level * 1e6)])
    noisy = lambda ts: [add_noise(t, sf, sx, rng)._replace(source=t.source) for t in ts]
    return data._replace(train=noisy(data.train), test=noisy(data.test)), info
