"""Synthetic ground truth: true parameters, batched simulation of force profiles, noisy
trajectories. Used by ``treeinfer simulate`` and ``demo``, the experiments and the benchmarks.

Data path: tree + true gains + force profiles [B, T] -> :func:`simulate_batch` (one batched
rollout, P = 1) -> :func:`synthetic_trajectories` (validated :class:`Trajectory` objects,
optional Gaussian noise) -> written by the caller with ``trajectories.write_trajectory`` and
``trajectories.write_true_params``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..data.trajectories import (
    Trajectory,
    add_noise,
    check_positive_params,
    read_true_params,
    validate_trajectory,
)
from ..errors import SimulationError, TreeinferError
from ..tree.description import Bounds, Tree

__all__ = [
    "TRUE_PARAMS_WINDOW",
    "default_true_params",
    "parse_params",
    "sim_tree",
    "simulate_batch",
    "synthetic_trajectories",
]

TRUE_PARAMS_WINDOW = (1.0 / 3.0, 2.0 / 3.0)  # share of each log prior box the truth is drawn in


def _depth(tree: Tree, name: str) -> int:
    return len(tree.ancestors(name))


def default_true_params(
    tree: Tree, rng: np.random.Generator, window: tuple[float, float] = TRUE_PARAMS_WINDOW
) -> tuple[np.ndarray, np.ndarray]:
    """Documented default ground truth: (kp [R] N m/rad, kd [R] N m s/rad).

    For Kp and for Kd separately, R fractions ``u`` are drawn uniformly in ``window`` (of the log
    prior box's width), sorted in decreasing order and given to the inferred joints from the
    root-most down (by depth), then mapped into each joint's box: ``lo * (hi / lo) ** u``. So
    every ancestor gets a fraction at least as large as its descendants', and, with one shared
    box, ``parent >= child`` for both Kp and Kd (the inequality prior's assumption).
    """
    lo, hi = tree.bounds_array()
    r = tree.n_inferred
    order = sorted(range(r), key=lambda j: _depth(tree, tree.inferred[j]))  # root-most first
    out = np.empty(2 * r)
    for block in (0, 1):  # Kp, then Kd
        u = np.sort(rng.uniform(window[0], window[1], size=r))[::-1]
        for rank, j in enumerate(order):
            k = block * r + j
            out[k] = lo[k] * (hi[k] / lo[k]) ** u[rank]
    return out[:r], out[r:]


def parse_params(
    tree: Tree, params: Sequence[float] | None = None, params_json: Path | None = None
) -> np.ndarray | None:
    """The true parameter vector [2R] (Kp of each inferred joint, then Kd; natural units) from
    a list (``--params``) or a JSON file (``--params-json``; see
    :func:`treeinfer.data.trajectories.read_true_params`), or None when neither is given."""
    if params is not None:
        return check_positive_params(params, tree.parameter_labels(), "--params")
    if params_json is None:
        return None
    return read_true_params(tree, params_json, where=f"--params-json {params_json}")


def sim_tree(tree: Tree, kp: np.ndarray) -> Tree:
    """The tree with each Kp prior box widened to contain the true Kp: the simulator picks its
    step from the stiffest corner of the box, so true values above it must still be stable."""
    bounds = {
        n: Bounds(kp=(b.kp[0], max(b.kp[1], float(k))), kd=b.kd)
        for (n, b), k in zip(tree.bounds.items(), kp)
    }
    return replace(tree, bounds=bounds)


def simulate_batch(
    tree: Tree,
    kp,
    kd,
    forces,
    dt: float,
    max_sim_dt: float | None = None,
    backend: str = "auto",
    log: Callable[[str], None] = lambda msg: None,
    force_interp: str = "linear",
    sim_tolerance: float | None = None,
    grasp_fraction=None,
):
    """One batched rollout of P = 1 parameter set (``kp``, ``kd`` [R]) under ``forces`` [B, T]
    (N, sampled every ``dt`` s): ``(Rollout [1, B, T] on the host, Simulator)``. The step is
    accuracy-controlled on these forces (``sim_tolerance`` m, default 0.1 mm; ``max_sim_dt`` s)
    with the forces interpolated as ``force_interp`` says; ``grasp_fraction`` as in
    :func:`treeinfer.sim.simulate` (only for choosing the step)."""
    import jax

    from . import DEFAULT_MAX_SIM_DT, make_simulator, simulate

    sim = make_simulator(
        sim_tree(tree, kp),
        obs_dt=dt,
        max_sim_dt=max_sim_dt or DEFAULT_MAX_SIM_DT,
        backend=backend,
        force_interp=force_interp,
        forces=np.asarray(forces, float),
        sim_tolerance=sim_tolerance,
        grasp_fraction=grasp_fraction,
    )
    slow = (
        " (MJX compiles for up to a minute on new shapes; cached afterwards)"
        if sim.backend == "mjx"
        else ""
    )
    log(f"simulating {forces.shape[0]} trajectories{slow}...")
    # simulate is jitted per simulator content: a second call on the same shapes reuses it
    rollout = simulate(sim, np.asarray(kp)[None], np.asarray(kd)[None], np.asarray(forces))
    return jax.device_get(rollout), sim


def synthetic_trajectories(
    rollout,
    forces: np.ndarray,
    dt: float,
    names: Sequence[str],
    noise_force: float = 0.0,
    noise_displacement: float = 0.0,
    rng_noise: np.random.Generator | None = None,
) -> list[Trajectory]:
    """Validated trajectories of parameter set 0 of ``rollout`` [1, B, T] under ``forces``
    [B, T], with Gaussian noise (sigma ``noise_force`` N, ``noise_displacement`` m) when asked.
    The simulator's velocity is kept unless the displacement is noisy (then readers
    differentiate the noisy displacement, as for a recording)."""
    t = np.arange(forces.shape[1], dtype=float) * dt
    out = []
    for i, name in enumerate(names):
        tau = np.asarray(rollout.tau[0, i], dtype=float)
        vel = np.asarray(rollout.tau_dot[0, i], dtype=float)
        traj = Trajectory(t, forces[i].copy(), tau, vel, name)
        if noise_force > 0 or noise_displacement > 0:
            traj = add_noise(traj, noise_force, noise_displacement, rng_noise)
            if noise_displacement == 0:  # the clean velocity is still the displacement's
                traj = traj._replace(velocity=vel)
            traj = traj._replace(source=name)
        try:
            traj = validate_trajectory(traj)
        except TreeinferError as e:
            raise SimulationError(f"simulated trajectory is implausible: {e}") from None
        out.append(traj)
    return out
