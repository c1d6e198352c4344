"""The one cache of the application layer: compiled simulators by (tree, obs_dt, substeps,
backend). A :class:`~treeinfer.sim.Simulator` is immutable and is a *static* jit argument hashed
by identity, so handing the same object to every predict() of a command reuses the traced and
compiled rollout instead of re-tracing the simulator (seconds; tens of seconds with MJX).

No module keeps one: a command (or a caller of :mod:`treeinfer.runs.service`) makes a
:class:`SimulatorCache` and passes it down; without one, each call builds its simulator.
"""

from __future__ import annotations

from ..sim import Simulator, make_simulator
from ..tree import Tree, tree_to_dict
from .provenance import tree_to_dict_json


class SimulatorCache:
    """At most ``max_size`` simulators, the oldest dropped first."""

    def __init__(self, max_size: int = 8):
        self.max_size = int(max_size)
        self._sims: dict[tuple, Simulator] = {}

    def __len__(self) -> int:
        return len(set(map(id, self._sims.values())))

    def get(
        self, tree: Tree, obs_dt: float, substeps: int | None = None, backend: str = "auto"
    ) -> Simulator:
        """:func:`treeinfer.sim.make_simulator` of these settings, built once."""
        tree_key = tree_to_dict_json(tree_to_dict(tree))
        sim = self._sims.get((tree_key, float(obs_dt), substeps, backend))
        if sim is None:
            sim = make_simulator(tree, obs_dt=float(obs_dt), substeps=substeps, backend=backend)
            while len(self._sims) >= self.max_size:
                self._sims.pop(next(iter(self._sims)))
            # under the requested and the resolved settings: a run folder records the resolved ones
            for b in {backend, sim.backend}:
                self._sims[(tree_key, float(obs_dt), substeps, b)] = sim
                self._sims[(tree_key, float(obs_dt), sim.substeps, b)] = sim
        return sim


def simulator_for(
    tree: Tree,
    obs_dt: float,
    substeps: int | None = None,
    backend: str = "auto",
    cache: SimulatorCache | None = None,
) -> Simulator:
    """The simulator of these settings from ``cache`` (built, and kept there, if missing); a new
    one when no cache is given."""
    return (cache if cache is not None else SimulatorCache()).get(tree, obs_dt, substeps, backend)
