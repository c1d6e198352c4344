"""Planar benchmark cases whose data come from an INDEPENDENT simulator (issue 27's targets).

The data of every case are rolled out by :class:`treeinfer.sim.planar_reference.PlanarTree`
(Lagrange's equations of a planar hinge chain integrated by scipy's DOP853), which shares no
code with treeinfer's MuJoCo/fused step: what a fit gets right here it gets right about the
physics, not about its own discretisation.

Cases (the chains of ``tests/test_accuracy.py``: tapering branches in a vertical plane, grasped
at 90% of the last one, the default prior box Kp 5-500 N m/rad, Kd 0.05-10 N m s/rad):

* ``chain2``: two joints (0.6 m + 0.4 m);
* ``chain3``: three joints (0.8 m + 0.6 m + 0.4 m).

Per seed (``numpy.random.SeedSequence([case index, seed]).spawn(4)``: truths, training pulls,
test pulls, noise): the true gains of :func:`treeinfer.sim.synthetic.default_true_params` (middle of
the log box, parent >= child, as ``treeinfer simulate`` draws them), training and UNSEEN test
pulls from :func:`treeinfer.data.random_specs` (``mixed``: ramp-hold-release and hold, peaks
2-8 N), then white noise: ``sigma_x`` on displacement and ``force_level`` times the largest
peak force of the data set on force (one sensor, one level), as ``experiments/coverage.py``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

SIGMA_X = 0.002  # m: displacement noise
FORCE_LEVEL = 0.02  # force noise: this share of the data set's largest peak force
CASES = ("chain2", "chain3")


def case_tree(name: str):
    """The tree of case ``name`` (``chain2`` or ``chain3``)."""
    from treeinfer.tree import chain
    from treeinfer.tree.description import Bounds

    n = {"chain2": 2, "chain3": 3}[name]
    return chain(
        n,
        [0.8, 0.6, 0.4][-n:],
        [0.025, 0.015, 0.01][-n:],
        angles_deg=[10.0, 15.0, -10.0][:n],
        grasp_fraction=0.9,
        bounds=Bounds(kp=(5.0, 500.0), kd=(0.05, 10.0)),
        base_pitch_deg=5.0,
        name=name,
    )


@dataclass
class Case:
    name: str
    seed: int
    tree: object
    kp: np.ndarray  # [R] true gains, in tree.inferred order
    kd: np.ndarray
    dt: float
    train_force: np.ndarray  # [B, T] N, clean
    train_tau: np.ndarray  # [B, T] m, clean (the reference's)
    test_force: np.ndarray
    test_tau: np.ndarray
    sigma_force: float  # N, the force noise's std


def make_case(
    name: str,
    seed: int,
    n_train: int = 3,
    n_test: int = 10,
    duration: float = 3.0,
    dt: float = 0.01,
    force_level: float = FORCE_LEVEL,
) -> Case:
    """The clean pulls of case ``name`` at ``seed`` (noise is added by :func:`noisy`)."""
    from treeinfer.data import from_spec, random_specs
    from treeinfer.sim.planar_reference import PlanarTree
    from treeinfer.sim.synthetic import default_true_params

    tree = case_tree(name)
    streams = [
        np.random.default_rng(s) for s in np.random.SeedSequence([CASES.index(name), seed]).spawn(4)
    ]
    kp, kd = default_true_params(tree, streams[0])
    ref = PlanarTree(tree, kp, kd)

    def pulls(n, rng):
        f = np.stack(
            [
                from_spec(s, duration, dt)
                for s in random_specs("mixed", n, duration, (2.0, 8.0), rng)
            ]
        )
        return f, np.stack([ref.rollout(row, dt) for row in f])

    train_f, train_t = pulls(n_train, streams[1])
    test_f, test_t = pulls(n_test, streams[2])
    sf = force_level * float(max(np.max(np.abs(train_f)), np.max(np.abs(test_f))))
    return Case(name, seed, tree, kp, kd, dt, train_f, train_t, test_f, test_t, sf)


def noisy(case: Case, sigma_x: float = SIGMA_X) -> tuple[tuple, tuple]:
    """``((train_force, train_tau), (test_force, test_tau))`` with the case's noise added
    (force noise ``case.sigma_force``, displacement ``sigma_x``; the noise stream of the seed)."""
    rng = np.random.default_rng(np.random.SeedSequence([CASES.index(case.name), case.seed, 3]))
    out = []
    for f, t in ((case.train_force, case.train_tau), (case.test_force, case.test_tau)):
        out.append(
            (
                f + rng.normal(0.0, case.sigma_force, f.shape) if case.sigma_force > 0 else f,
                t + rng.normal(0.0, sigma_x, t.shape) if sigma_x > 0 else t,
            )
        )
    return out[0], out[1]


def write_folder(path: Path, tree, kp, kd, force: np.ndarray, tau: np.ndarray, dt: float, tag: str):
    """A data folder ``treeinfer infer``/``evaluate`` read: ``<tag><i>.csv`` per pull (no
    velocity column: treeinfer differentiates the recorded displacement, as for a recording)
    and ``true_params.json`` (so ``evaluate`` reports the posterior against the truth)."""
    from treeinfer.data.trajectories import Trajectory, write_trajectory

    path.mkdir(parents=True, exist_ok=True)
    t = np.arange(force.shape[1]) * dt
    for i, (f, x) in enumerate(zip(force, tau)):
        write_trajectory(path / f"{tag}{i}.csv", Trajectory(t, f, x, None, f"{tag}{i}"))
    truth = {
        "kp": {j: float(v) for j, v in zip(tree.inferred, kp)},
        "kd": {j: float(v) for j, v in zip(tree.inferred, kd)},
    }
    (path / "true_params.json").write_text(json.dumps(truth, indent=2) + "\n")
