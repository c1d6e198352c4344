"""Quasi-static pushes: the equilibrium of the hinge tree under each force sample.

A slow displacement-controlled test (a stepper pushing a stem, samples every 0.1-1 s for tens
of seconds) passes through equilibria: inertia and damping leave no trace in it. For such data
the *static model* replaces the rollout: for every force sample ``f_t`` it solves

    0 = -Kp (q - q_spring) - qfrc_bias(q) + J_C(q)^T (f_t d)

(spring, gravity, and the point force ``f_t`` along the unit direction ``d`` at the grasp point
C, whose generalised force is the transpose of C's positional Jacobian times the force), by the
clipped Newton iteration of the simulator's settle solver (:func:`treeinfer.sim.settle`)
with exact Jacobians from ``jax.jacfwd``. The samples are independent (no time stepping), so
they are solved in one ``vmap`` over particles x profiles x samples. The observed displacement
is ``tau_t = (C(q_t) - C(q_rest)) . d``. Only stiffness is identified; damping is not
(:func:`damping_note`).

:func:`natural_periods` and :func:`suggest_static` tell when a data set is quasi-static (its
sample interval far longer than the branch's slowest natural period), and
:func:`parameter_layout` gives the theta layout for inferring stiffness only
(``inference: {parameters: [kp]}``) with any model.

:func:`static_equilibria` returns the joint angles of those equilibria instead of the grasp
point's displacement (for inclinometer observations, :mod:`treeinfer.inference.pulltest`).

Modules: :mod:`~treeinfer.inference.static.equilibrium` (the solver),
:mod:`~treeinfer.inference.static.detection` (quasi-static data),
:mod:`~treeinfer.inference.static.layout` (theta layouts, model kinds),
:mod:`~treeinfer.inference.static.model` (:class:`Model`, rollouts, per-recording pulls) and
:mod:`~treeinfer.inference.static.terms` (likelihood terms of any model) and
:mod:`~treeinfer.inference.static.posterior` (the Laplace approximation from exact derivatives).
"""

from __future__ import annotations

from ...tree.description import PARAMETERS, parse_parameters
from .detection import QUASI_STATIC_RATIO, natural_periods, quasi_static_notice, suggest_static
from .equilibrium import NEWTON_CLIP, Equilibria, static_equilibria, static_rollout
from .layout import (
    MODEL_KINDS,
    ParameterLayout,
    damping_note,
    parameter_layout,
    parse_model_kind,
    run_tree,
    tree_layout,
    with_tie,
)
from .model import Model, model_for, model_rollout, model_with_pulls
from .posterior import exact_laplace
from .terms import (
    StaticForceNoise,
    compliance_slopes,
    effective_noise,
    force_noise_estimate,
    full_theta,
    model_likelihood_terms,
    static_force_noise_for,
)
from .tied import TiedLayout, taper_shape, tied_layout, tree_tied_layout

__all__ = [
    "Equilibria",
    "MODEL_KINDS",
    "Model",
    "NEWTON_CLIP",
    "PARAMETERS",
    "QUASI_STATIC_RATIO",
    "ParameterLayout",
    "StaticForceNoise",
    "TiedLayout",
    "compliance_slopes",
    "damping_note",
    "effective_noise",
    "exact_laplace",
    "force_noise_estimate",
    "full_theta",
    "natural_periods",
    "parameter_layout",
    "model_for",
    "model_likelihood_terms",
    "model_rollout",
    "model_with_pulls",
    "parse_model_kind",
    "parse_parameters",
    "quasi_static_notice",
    "run_tree",
    "static_force_noise_for",
    "static_equilibria",
    "static_rollout",
    "taper_shape",
    "tied_layout",
    "tree_tied_layout",
    "with_tie",
    "suggest_static",
    "tree_layout",
]
