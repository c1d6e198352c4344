"""A finished run as the starting point: the service behind ``treeinfer suggest``."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..design.candidates import Target, candidate_grid, parse_target
from ..design.scoring import Suggestions, plot_scores, score_candidates
from ..errors import ConfigError


def noise_sigma_of_run(config: dict) -> tuple[float, str]:
    """``(sigma_x m, where it came from)`` for a run's ``config.json``.

    A run that records a Gaussian noise model (``problem.sigma_x`` or ``options.sigma_x``, as
    the noise-model issue adds) gives it directly; an older run gets the displacement noise its
    Boltzmann temperature stands for, inverting :func:`treeinfer.model.likelihood.suggest_kT` at the
    data's length and time step (``kT = sigma sqrt(T) (1 + 1 / (sqrt 2 dt))``)."""
    for where in ("problem", "options", "noise"):
        sec = config.get(where) or {}
        for key in ("sigma_x", "sigma_displacement", "sigma_x_m"):
            if isinstance(sec.get(key), (int, float)) and sec[key] > 0:
                return float(sec[key]), f"{where}.{key}"
    p = config.get("problem") or {}
    try:
        kT, dt, t = float(p["kT"]), float(p["obs_dt"]), int(p["n_steps"])
    except (KeyError, TypeError, ValueError):
        raise ConfigError(
            "run config: no noise model and no kT/obs_dt/n_steps to derive one from; give sigma_x"
        ) from None
    return kT / (
        math.sqrt(t) * (1.0 + 1.0 / (math.sqrt(2.0) * dt))
    ), "derived from kT (suggest_kT inverted)"


def suggest_for_run(
    run_dir,
    grasp_fractions: Sequence[float] = tuple(np.round(np.linspace(0.1, 1.0, 10), 2)),
    peak_forces: Sequence[float] = (2.0, 4.0, 6.0, 8.0),
    profile_kinds: Sequence[str] = ("ramp",),
    directions: Sequence | None = None,
    target: Target | str | None = None,
    parameter: str | None = None,
    sigma_x: float | None = None,
    duration: float | None = None,
    n_particles: int = 32,
    seed: int = 0,
    out=None,
    force: bool = False,
    formats=None,
    allow_modified: bool = False,
) -> Suggestions:
    """Score candidate next pulls for the posterior of a finished run folder.

    ``sigma_x`` (m) defaults to :func:`noise_sigma_of_run`; ``duration`` (s) to the run's
    training trajectory length. With ``out``, writes ``suggestions.json`` (the ranked table,
    settings, run path) and ``suggestions.png`` (:func:`plot_scores`) there, as one folder
    (``force`` moves a previous one aside, never deletes it; ``out`` may not be, hold or lie in
    the run, except ``RUN/suggest``). ``allow_modified``: score a run whose files changed since
    ``infer`` wrote them (:func:`treeinfer.runs.load_run`); what changed is recorded in the
    settings (``integrity_notes``). Returns the :class:`Suggestions`."""
    from pathlib import Path

    from ..io.atomic import atomic_write_json, check_output_dir, staged_output_dir
    from . import load_run

    if out is not None:  # before any work; RUN/suggest (the CLI's default) is the run's own
        where = {"inputs": [run_dir], "allow_inside": [Path(run_dir) / "suggest"]}
        check_output_dir(out, force, "suggestions", **where)
    run = load_run(run_dir, allow_modified=allow_modified)
    noise_from = "given"
    if sigma_x is None:
        sigma_x, noise_from = noise_sigma_of_run(run.config)
    if duration is None:
        p = run.config.get("problem", {})
        duration = float(p.get("n_steps", 0)) * run.sim.obs_dt
        if not duration > 0:
            raise ConfigError(
                f"{run_dir}: cannot tell the pull duration from the run; give duration"
            )
    if isinstance(target, str):
        target = parse_target(target)
    cands = candidate_grid(grasp_fractions, peak_forces, profile_kinds, directions)
    sugg = score_candidates(
        run.sim,
        # the gains only: a generative likelihood's run has its noise columns after them
        np.asarray(run.theta)[:, : 2 * run.sim.n_joints],
        cands,
        float(sigma_x),
        float(duration),
        valid=run.stable,
        n_particles=n_particles,
        target=target,
        parameter=parameter,
        seed=seed,
    )
    sugg = sugg._replace(
        settings={
            **sugg.settings,
            "run": str(Path(run_dir).resolve()),
            "sigma_x_from": noise_from,
            "labels": list(run.labels),
            **({"integrity_notes": list(run.notes)} if run.notes else {}),
        }
    )
    if out is not None:
        import matplotlib.pyplot as plt

        from ..evaluation.plots import save_figure

        with staged_output_dir(out, force, "suggestions", **where) as stage:
            atomic_write_json(stage / "suggestions.json", sugg.to_dict())
            fig, _ = plot_scores(sugg)
            save_figure(fig, stage / "suggestions.png", formats=formats)
            plt.close(fig)
    return sugg
