"""Programs that take what they close over as arguments: compiled once per shape, not once per
recording.

The amortised check (:mod:`treeinfer.amortised.check`) weights the flow's draws with the start
pipeline's rollout program (:class:`treeinfer.inference.fast_evaluator.BatchEvaluator`), which
takes the recording as an argument. Three smaller programs around it did not: the log-prior
(its noise column's bounds come from the recording's range and resolution), the noise density
(its mask and force-noise basis are the recording's) and the Gauss-Newton terms of the LM fit
(both of them, differentiated). Each was a ``jax.jit`` of a closure over the run's problem, so
every new recording compiled all three again: 4.6 s of the 1-joint chain's 5.5 s check on the
2-core CPU (and the persistent compile cache could not help: the recording's numbers are
constants of the program text).

:class:`ArgsProgram` traces such a function to a jaxpr (milliseconds), lifts the jaxpr's
constants -- the closed-over arrays and the scalar literals, where the recording's numbers
are -- into arguments, and compiles one program per lifted jaxpr's *text* (shapes, dtypes and
operations; no values): a second recording of the same shape traces again and runs the
program already compiled. The values are the function's own (the same jaxpr evaluated),
``tests/test_amortised_programs.py`` checks both.

Why not rewrite the prior and the noise density with the data as parameters (as
``LikelihoodTerms.loglik_of`` does for the likelihood): they are assembled from several
modules (the box, the noise prior, the learned inequality prior, the force-noise term), and a
copy would drift from the problem's own; the lifted jaxpr *is* the problem's.
"""

from __future__ import annotations

from ..sim.args_program import ArgsProgram, lift_constants

__all__ = ["ArgsProgram", "lift_constants", "with_argument_programs"]


def with_argument_programs(ev, programs=None):
    """``ev`` (a :class:`~treeinfer.inference.fast_evaluator.BatchEvaluator`) with its log-prior,
    noise density and Gauss-Newton programs (:func:`treeinfer.inference.start_steps.ggn_terms`'
    program, which the evaluator keeps as ``_ggn``) replaced by :class:`ArgsProgram` s of the
    same functions, their programs in ``programs`` (as :class:`ArgsProgram`'s): the rollout
    program already takes the recording as an argument, these then do too. Returns ``ev``.

    Written here, on the evaluator's attributes, because the check is where a process meets
    many recordings of one shape (a robot's); the start pipeline's own evaluator could take the
    same programs (its per-recording compilations are the same three)."""
    if isinstance(ev._prior, ArgsProgram):
        # built with a program cache, the evaluator already made them (BatchEvaluator._program)
        return ev
    ev._prior = ArgsProgram(ev.problem.log_prior, programs)
    if ev._noise is not None:
        ev._noise = ArgsProgram(ev.problem.noise.residual_loglik, programs)
        from ..inference.start_steps import _ggn_program

        ev._ggn = ArgsProgram(_ggn_program(ev), programs)
    return ev
