"""The one cache of the application layer: compiled simulators by (tree, obs_dt, substeps,
backend), and the command's compiled sampler programs (``SimulatorCache.programs``, a
:class:`~treeinfer.sim.program_cache.ProgramCache` handed to
:func:`treeinfer.inference.problem.infer`).

A :class:`~treeinfer.sim.Simulator` is immutable and is a *static* jit argument hashed by
identity, so handing the same object to every predict() of a command reuses the traced and
compiled rollout instead of re-tracing the simulator (seconds; tens of seconds with MJX).

No module keeps one: a command (or a caller of :mod:`treeinfer.runs.service`) makes a
:class:`SimulatorCache` and passes it down; without one, each call builds its simulator and
compiles its programs.
"""

from __future__ import annotations

import hashlib

import numpy as np

from ..io.provenance import tree_to_dict_json
from ..sim import Simulator, make_simulator
from ..sim.program_cache import ProgramCache
from ..tree.description import Tree, tree_to_dict


class SimulatorCache:
    """At most ``max_size`` simulators, the oldest dropped first, and ``programs``: the
    command's :class:`~treeinfer.sim.program_cache.ProgramCache` of compiled sampler programs (at
    most ``max_size`` too), which :mod:`treeinfer.runs.service` passes to every sampler run."""

    def __init__(self, max_size: int = 8):
        self.max_size = int(max_size)
        self._sims: dict[tuple, Simulator] = {}
        self.programs = ProgramCache(self.max_size)
        self._jacobian_programs: dict = {}  # see get()

    def __len__(self) -> int:
        return len(set(map(id, self._sims.values())))

    def get(
        self,
        tree: Tree,
        obs_dt: float,
        substeps: int | None = None,
        backend: str = "auto",
        *,
        force_interp: str = "linear",
        max_sim_dt: float | None = None,
        sim_tolerance: float | None = None,
        forces=None,
        grasp_fraction=None,
    ) -> Simulator:
        """:func:`treeinfer.sim.make_simulator` of these settings, built once. With ``forces``
        [B, T] (the data's) and no ``substeps``, the step is accuracy-controlled on them
        (``sim_tolerance``, m; ``max_sim_dt``, s; ``grasp_fraction`` of the data)."""
        tree_key = tree_to_dict_json(tree_to_dict(tree))
        # with substeps given the step bounds do not matter: a run folder's recorded settings
        extra: tuple = (force_interp,)
        if substeps is None:
            extra += (max_sim_dt, sim_tolerance)
        if substeps is None and forces is not None:
            f = np.ascontiguousarray(np.asarray(forces, np.float64))
            g = None if grasp_fraction is None else np.asarray(grasp_fraction, float).tobytes()
            extra += (hashlib.sha256(f.tobytes()).hexdigest(), f.shape, g)
        sim = self._sims.get((tree_key, float(obs_dt), substeps, backend, extra))
        if sim is None:
            kw = {} if max_sim_dt is None else {"max_sim_dt": float(max_sim_dt)}
            if substeps is None and forces is not None:
                kw.update(forces=np.asarray(forces, float), grasp_fraction=grasp_fraction)
                kw["sim_tolerance"] = sim_tolerance
            elif substeps is None and sim_tolerance is not None:
                kw["sim_tolerance"] = sim_tolerance
            sim = make_simulator(
                tree,
                obs_dt=float(obs_dt),
                substeps=substeps,
                backend=backend,
                force_interp=force_interp,
                **kw,
            )
            # the force-noise Jacobian's compiled programs are shared by every simulator of this
            # cache (they are keyed by the program's content): a second data set of the same
            # shapes (batch, k-fold) builds a new simulator but reuses its program
            sim.derived["force_jacobian_programs"] = self._jacobian_programs
            while len(self._sims) >= self.max_size:
                self._sims.pop(next(iter(self._sims)))
            # under the requested and the resolved settings: a run folder records the resolved ones
            resolved = (force_interp,)
            for b in {backend, sim.backend}:
                self._sims[(tree_key, float(obs_dt), substeps, b, extra)] = sim
                self._sims[(tree_key, float(obs_dt), sim.substeps, b, resolved)] = sim
        return sim


def simulator_for(
    tree: Tree,
    obs_dt: float,
    substeps: int | None = None,
    backend: str = "auto",
    cache: SimulatorCache | None = None,
    **kwargs,
) -> Simulator:
    """The simulator of these settings from ``cache`` (built, and kept there, if missing); a new
    one when no cache is given. ``kwargs``: :meth:`SimulatorCache.get`'s (force interpolation,
    step bounds, the data's forces for the accuracy-controlled step)."""
    c = cache if cache is not None else SimulatorCache()
    return c.get(tree, obs_dt, substeps, backend, **kwargs)
