"""The independent planar-chain reference, kept importable as ``planar_chain`` for the tests: it
lives in :mod:`treeinfer.sim.planar_reference` so that experiments can use it without importing
the tests folder."""

from treeinfer.sim.planar_reference import PlanarTree

__all__ = ["PlanarTree"]
