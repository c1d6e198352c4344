"""Programs that take what they close over as arguments: compiled once per argument shape and
program text, not once per recording.

The start pipeline's rollout program (:class:`treeinfer.inference.fast_evaluator.BatchEvaluator`)
takes the recording as an argument; the smaller programs around it -- the log-prior (its noise
column's bounds come from the recording's range), the noise density (its mask, force-noise
basis and integration-error floor are the recording's) and the Gauss-Newton terms of the LM
fit -- are closures over the run's problem, so a ``jax.jit`` of them compiled again for every
recording, in a batch's worker as in a new process (the persistent compile cache could not
help: the recording's numbers were constants of the program text).

:class:`ArgsProgram` traces such a function to a jaxpr (milliseconds), lifts the jaxpr's
constants -- the closed-over arrays and the scalar literals, where the recording's numbers
are -- into arguments, and compiles one program per lifted jaxpr's *text* (shapes, dtypes and
operations; no values): a second recording of the same shape traces again and runs the
program already compiled. The values are the function's own (the same jaxpr evaluated),
``tests/test_amortised_programs.py`` checks both. Written for the amortised check
(:mod:`treeinfer.amortised.programs`), which meets many recordings of one shape; kept here, beside
:mod:`treeinfer.sim.program_cache`, because the start pipeline uses it too.

Why not rewrite the prior and the noise density with the data as parameters (as
``LikelihoodTerms.loglik_of`` does for the likelihood): they are assembled from several
modules (the box, the noise prior, the learned inequality prior, the force-noise term, the
integration-error floor), and a copy would drift from the problem's own; the lifted jaxpr *is*
the problem's.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import numpy as np

__all__ = ["ArgsProgram", "lift_constants"]


def lift_constants(fn: Callable, *args):
    """``(key, jaxpr, consts, out_tree)``: ``fn`` traced at ``args`` (arrays) with every constant
    of its top-level jaxpr -- closed-over arrays and literals -- turned into a leading input;
    ``consts`` their values, ``key`` the lifted jaxpr's text (no values). Literals inside nested
    jaxprs (``jit``-ed helpers, control flow) stay: a recording's number there gives another
    key, so another program (correct, only not shared)."""
    from jax.extend.core import Jaxpr, Literal, Var

    closed, shapes = jax.make_jaxpr(fn, return_shape=True)(*args)
    jp = closed.jaxpr
    lit_vars, lit_vals, eqns = [], [], []

    def lifted(v):
        if not isinstance(v, Literal):
            return v
        nv = Var(v.aval)
        lit_vars.append(nv)
        lit_vals.append(np.asarray(v.val, dtype=v.aval.dtype))
        return nv

    for eqn in jp.eqns:
        eqns.append(eqn.replace(invars=[lifted(v) for v in eqn.invars]))
    outvars = [lifted(v) for v in jp.outvars]
    new = Jaxpr(
        constvars=[],
        invars=[*jp.constvars, *lit_vars, *jp.invars],
        outvars=outvars,
        eqns=eqns,
        effects=jp.effects,
    )
    consts = [*closed.consts, *lit_vals]
    out_tree = jax.tree_util.tree_structure(shapes)
    return str(new) + "\n" + str(out_tree), new, consts, out_tree


def _build(jaxpr) -> Callable:
    from jax.extend.core import ClosedJaxpr, jaxpr_as_fun

    run = jaxpr_as_fun(ClosedJaxpr(jaxpr, []))
    return jax.jit(lambda consts, *args: run(*consts, *args))


class ArgsProgram:
    """``fn`` (arrays in, a pytree of arrays out) run as one compiled program per argument
    shape and lifted jaxpr (module docstring): a drop-in for ``jax.jit(fn)`` where ``fn``
    closes over a recording's data. The programs live in ``programs`` (a
    :class:`~treeinfer.sim.program_cache.ProgramCache`, keyed by the lifted jaxpr's text), shared
    by every ArgsProgram handed the same cache (the amortised model keeps one:
    :attr:`treeinfer.amortised.estimator.Amortised.programs`); None: this instance's own.
    ``traces`` counts the traces (one per argument shape)."""

    def __init__(self, fn: Callable, programs=None):
        from ..sim.program_cache import ProgramCache

        # a jitted fn would trace to one nested call whose literals stay inside: its body
        self.fn = getattr(fn, "__wrapped__", fn)
        self.programs = ProgramCache() if programs is None else programs
        self._by_shape: dict = {}
        self.traces = 0

    def __call__(self, *args):
        shape_key = tuple((np.shape(a), str(getattr(a, "dtype", type(a)))) for a in args)
        hit = self._by_shape.get(shape_key)
        if hit is None:
            key, jaxpr, consts, out_tree = lift_constants(self.fn, *args)
            self.traces += 1
            prog = self.programs.get(("ArgsProgram", key), lambda: _build(jaxpr))
            hit = self._by_shape[shape_key] = (prog, consts, out_tree)
        prog, consts, out_tree = hit
        return jax.tree_util.tree_unflatten(out_tree, prog(consts, *args))
