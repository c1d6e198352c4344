"""Particles sharded across devices: every device simulates its own particles and their
finite-difference perturbations; the SVGD kernel term, which couples all particles, gets them
through an XLA collective inside the same jitted step (never through the host).

    mesh = particle_mesh()                          # all local devices, one axis "particles"
    posterior = infer_sharded(problem, "nnsvgd", n_particles=1024, mesh=mesh)

or, piece by piece (what :func:`infer_sharded` does):

    sharded = shard_problem(problem, mesh)          # value_and_grad / log_density split by particle
    theta0 = shard_particles(initial_particles(problem, 1024), mesh)
    posterior = infer(sharded, "nnsvgd", n_particles=1024, initial_theta=theta0)

How the work is split:

* ``value_and_grad`` (the batched central difference of the likelihood plus the priors) gets
  its particle axis split along the mesh: a device holding P/n particles builds their
  P/n * (2D + 1) perturbed rows and simulates them. Rows are independent, so no communication
  is needed here. Two ways, same result: ``method="gspmd"`` (default) puts sharding constraints
  on the particle axis at the function's input and output and lets XLA's SPMD partitioner split
  the batched simulator; ``method="shard_map"`` writes the per-device program explicitly with
  :func:`jax.shard_map`. Why GSPMD is the default: with jax/jaxlib 0.11.2 on two H200s, XLA's GPU
  compiler crashed (segmentation fault in ``backend_compile_and_load``) on the ``shard_map``
  version of the MJX likelihood, while the GSPMD version compiled and ran (CPU: both work).
* The Stein direction ``phi(x_i) = 1/P sum_j k(x_j, x_i) grad_j + grad_{x_j} k(x_j, x_i)`` and
  the median-heuristic bandwidth need every particle. The sampler step is jitted with sharded
  operands, so XLA's SPMD partitioner inserts the collectives (all-gather of particles/gradients,
  all-reduce of partial sums) on the devices' interconnect; the test checks the compiled step
  contains them and that positions stay sharded between iterations.

Reproducibility: with the same seed, a sharded run gives the same particles as an unsharded
one to float32 rounding, not guaranteed bit for bit (per-device programs see a smaller batch and
XLA may round differently; on two CPU devices a cheap target gave identical bits, the MJX
likelihood agreed to ~1e-5 relative); ``tests/test_sharding.py`` checks this on two CPU devices.

Multi-host: start every process with ``jax.distributed.initialize()`` (see ``BENCHMARKS.md``),
then ``particle_mesh()`` spans all processes' devices and :func:`shard_particles` builds the
global array from the (identical, seeded) host copy each process holds. Untested; the sampler
driver's host copies (``np.asarray`` of positions and trace) would need
``jax.experimental.multihost_utils.process_allgather`` there.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from ..errors import ConfigError
from ..model.gradients import LogDensityFn, ValueAndGradFn

__all__ = [
    "AXIS",
    "infer_sharded",
    "particle_mesh",
    "particle_sharding",
    "shard_log_density",
    "shard_particles",
    "shard_problem",
    "shard_value_and_grad",
]

AXIS = "particles"
"""Name of the mesh axis the particles are split along."""


def particle_mesh(devices=None) -> Mesh:
    """A one-axis mesh (``"particles"``) over ``devices`` (default: ``jax.devices()``, i.e. every
    device of every process)."""
    devices = jax.devices() if devices is None else list(devices)
    if not devices:
        raise ConfigError("particle_mesh: no devices given")
    return Mesh(np.asarray(devices), (AXIS,))


def particle_sharding(mesh: Mesh | None = None) -> NamedSharding:
    """Leading (particle) axis split over the mesh, other axes replicated."""
    return NamedSharding(particle_mesh() if mesh is None else mesh, P(AXIS))


def _check_divisible(n_particles: int, mesh: Mesh, what: str) -> None:
    n_dev = mesh.shape[AXIS]
    if n_particles % n_dev:
        raise ConfigError(
            f"{what}: {n_particles} particles cannot be split evenly over {n_dev} devices; "
            f"use a multiple of {n_dev}"
        )


def shard_particles(theta, mesh: Mesh | None = None) -> jax.Array:
    """``theta [P, D]`` as a global array split by particle over ``mesh``.

    ``theta`` may be a host array or a JAX array; in a multi-process run every process must
    pass the same values (e.g. drawn with the same seed). ``P`` must be a multiple of the number
    of devices."""
    mesh = particle_mesh() if mesh is None else mesh
    host = np.asarray(theta)
    if host.ndim != 2:
        raise ConfigError(f"shard_particles: theta must have shape [P, D], got {host.shape}")
    _check_divisible(host.shape[0], mesh, "shard_particles")
    return jax.make_array_from_callback(host.shape, particle_sharding(mesh), lambda idx: host[idx])


def _constrained(fn, mesh: Mesh):
    """``fn`` with its particle axis constrained to be split over ``mesh`` at input and output;
    XLA's SPMD partitioner splits the (row-independent) work in between."""
    split = particle_sharding(mesh)

    def wrapped(theta):
        _check_divisible(theta.shape[0], mesh, "sharded evaluation")
        out = fn(jax.lax.with_sharding_constraint(theta, split))
        return jax.tree.map(lambda x: jax.lax.with_sharding_constraint(x, split), out)

    return wrapped


def shard_value_and_grad(
    value_and_grad: ValueAndGradFn, mesh: Mesh | None = None, method: str = "gspmd"
) -> ValueAndGradFn:
    """``value_and_grad(theta [P, D]) -> ([P], [P, D])`` evaluated per device on its block of
    particles (``shard_map``): each device runs the simulator once, on its own particles'
    P/n * (2D + 1) finite-difference rows. Jittable; P must be a multiple of the device count.

    ``check_vma=False``: the wrapped function is per-device code with no collectives, and MJX's
    loops mix device-varying and replicated carries, which the check would reject."""
    mesh = particle_mesh() if mesh is None else mesh
    if method == "gspmd":
        return _constrained(value_and_grad, mesh)
    _check_method(method)
    mapped = jax.shard_map(
        value_and_grad, mesh=mesh, in_specs=P(AXIS), out_specs=(P(AXIS), P(AXIS)), check_vma=False
    )

    def sharded(theta):
        _check_divisible(theta.shape[0], mesh, "value_and_grad")
        return mapped(theta)

    return sharded


def _check_method(method: str) -> None:
    if method not in ("shard_map", "gspmd"):
        raise ConfigError(f"sharding method: expected 'shard_map' or 'gspmd', got {method!r}")


def shard_log_density(
    log_density: LogDensityFn, mesh: Mesh | None = None, method: str = "gspmd"
) -> LogDensityFn:
    """``log_density(theta [P, D]) -> [P]`` evaluated per device on its block of particles."""
    mesh = particle_mesh() if mesh is None else mesh
    if method == "gspmd":
        return _constrained(log_density, mesh)
    _check_method(method)
    mapped = jax.shard_map(
        log_density, mesh=mesh, in_specs=P(AXIS), out_specs=P(AXIS), check_vma=False
    )

    def sharded(theta):
        _check_divisible(theta.shape[0], mesh, "log_density")
        return mapped(theta)

    return sharded


def shard_problem(problem, mesh: Mesh | None = None, method: str = "gspmd"):
    """A copy of a :class:`~treeinfer.inference.problem.Problem` whose ``value_and_grad`` and
    ``log_density`` run sharded over ``mesh`` (everything else shared with ``problem``).

    ``method``: ``"shard_map"`` (explicit per-device programs) or ``"gspmd"`` (sharding
    constraints on the particle axis; XLA partitions the row-independent simulator work)."""
    mesh = particle_mesh() if mesh is None else mesh
    return dataclasses.replace(
        problem,
        value_and_grad=shard_value_and_grad(problem.value_and_grad, mesh, method),
        log_density=shard_log_density(problem.log_density, mesh, method),
        settings={**problem.settings, "sharded_over_devices": int(mesh.shape[AXIS])},
    )


def infer_sharded(
    problem,
    sampler: str = "nnsvgd",
    n_particles: int = 64,
    seed: int = 0,
    mesh: Mesh | None = None,
    method: str = "gspmd",
    **infer_options,
):
    """:func:`treeinfer.infer` with particles sharded over ``mesh`` (default: all devices).

    Same initial particles and keys as the unsharded ``infer`` with this seed, so the result
    matches it to float32 rounding. ``n_particles`` must be a multiple of the device count;
    ``method`` as in :func:`shard_problem`; other options go to ``infer``."""
    from .problem import check_count, infer, initial_particles

    mesh = particle_mesh() if mesh is None else mesh
    check_count(n_particles, "n_particles")
    _check_divisible(n_particles, mesh, "infer_sharded")
    if "initial_theta" in infer_options and infer_options["initial_theta"] is not None:
        theta0 = infer_options.pop("initial_theta")
    else:
        infer_options.pop("initial_theta", None)
        theta0 = initial_particles(problem, n_particles, seed)
    return infer(
        shard_problem(problem, mesh, method),
        sampler,
        n_particles=n_particles,
        seed=seed,
        initial_theta=shard_particles(theta0, mesh),
        **infer_options,
    )
