"""The run folder ``RUN/``: summaries, save (staged, atomic) and load."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import __version__
from ..errors import ConfigError
from ..evaluation.predictive import LEVEL
from ..inference.posterior_io import UNITS  # one table of units (moved there, issue 29)
from ..inference.samplers import sampler_spec
from ..io.atomic import atomic_write_bytes, atomic_write_text, staged_output_dir
from ..io.jsonio import read_json, write_json
from ..tree.description import Tree, dump_tree, load_tree
from .cache import SimulatorCache, simulator_for
from .checkpoint import _npz_bytes, partial_dir
from .config import RUN_FORMAT


# ==== summaries ===================================================================================
def posterior_table(theta, labels, valid=None, level: float = LEVEL) -> dict:
    """``{label: {mean, lower, upper, unit}}`` in natural units: the particle mean of the gain and
    the central ``level`` interval of the per-parameter KDE in log space, mapped back by ``exp``."""
    from ..evaluation.metrics import predictive_interval

    theta = np.asarray(theta, float)
    ok = np.all(np.isfinite(theta), axis=1) & (True if valid is None else np.asarray(valid, bool))
    out = {}
    if ok.sum() >= 2:
        lo, hi, _ = (np.asarray(a) for a in predictive_interval(theta, level, ok))
    else:
        lo = hi = np.full(theta.shape[1], np.nan)
    from ..model.likelihood import natural_units

    nat = natural_units(theta[ok], labels) if ok.any() else np.zeros((0, len(labels)))
    bounds = natural_units(np.stack([lo, hi]), labels)  # monotone maps: interval ends map over
    for j, lab in enumerate(labels):
        k = nat[:, j]
        out[lab] = {
            "mean": float(k.mean()) if k.size else float("nan"),
            "median": float(np.median(k)) if k.size else float("nan"),
            "lower": float(bounds[0, j]),
            "upper": float(bounds[1, j]),
            "unit": UNITS[lab.split("[")[0]],
        }
    return out


def _bandwidths(positions: np.ndarray) -> np.ndarray:
    from ..inference.samplers import median_length_scale

    if len(positions) == 0:
        return np.zeros(0)
    return np.asarray(jax.jit(jax.vmap(median_length_scale))(jnp.asarray(positions)), float)


def run_bandwidths(trace: dict, sampler: str):
    """The trace plot's kernel bandwidths per iteration (SVGD samplers), else None."""
    return _bandwidths(trace["positions"]) if sampler_spec(sampler).family == "svgd" else None


def _diagnostics(
    sampler: str, trace: dict, labels, warmup: float = 0.5
) -> tuple[str, dict, list[str]]:
    """Convergence diagnostics of the run's trace. MCMC: R-hat/ESS over every chain after the
    run's own warm-up share (``--mcmc-warmup``), the draws the summaries report (one meaning of
    the option: the warm-up is discarded from both)."""
    from ..inference.diagnostics import convergence_warnings, mcmc_diagnostics, svgd_diagnostics

    kind = sampler_spec(sampler).family
    try:
        if kind == "svgd":
            ksd = trace.get("diagnostics", {}).get("ksd")
            diag = svgd_diagnostics(
                trace["log_density"],
                _bandwidths(trace["positions"]),
                ksd_trace=ksd if ksd is not None and len(ksd) >= 2 else None,
            )
        else:
            diag = mcmc_diagnostics(
                trace["positions"], labels, burn_in=warmup, log_density=trace["log_density"]
            )
        warns = convergence_warnings(diag, kind)
    except ConfigError as e:  # e.g. too short a trace for split R-hat
        diag, warns = {"error": str(e)}, [f"diagnostics unavailable: {e}"]
    if trace["resumed_from"] is not None:
        diag["resumed_from"] = trace["resumed_from"]
    return kind, diag, warns


def _reinitialised(run) -> int:
    """Particle moves by ``--reinit-stragglers`` over the run (the driver's per-iteration
    ``n_reinitialised`` diagnostic, summed; 0 when the remedy was off or found none)."""
    diag = getattr(run, "diagnostics", None) or {}
    n = diag.get("n_reinitialised") if isinstance(diag, dict) else None
    if n is None:
        return 0
    parts = n if isinstance(n, (list, tuple)) else [n]  # per chunk, or already concatenated
    return int(sum(np.sum(np.asarray(x, float)) for x in parts))


def _straggler_and_edge(problem, posterior) -> tuple[dict, dict]:
    """Stuck particles among the final ones and posterior mass beyond a prior-box edge (issue
    11): both warn in summary.json's ``convergence_warnings`` and on the CLI."""
    from ..inference.diagnostics import find_stragglers, prior_edge_mass

    labels = list(problem.labels)
    # the sampler's own final particles (before --drop-stragglers or MCMC draws replace them)
    run = posterior.run
    raw = (np.asarray(run.final_positions), np.asarray(run.final_state.logdensity))
    rep = find_stragglers(raw[1], raw[0], problem.lower, problem.upper, labels=labels)
    strag = {
        "n_stragglers": rep.n_stragglers,
        "particles": np.flatnonzero(rep.mask).tolist(),
        "n_low_density": int(rep.low_density.sum()),
        "n_outside_box": int(rep.outside_box.sum()),
        "n_nonfinite": int(rep.nonfinite.sum()),
        "dropped": bool(getattr(posterior, "settings", {}).get("dropped_stragglers", False)),
        "warnings": [w for w in rep.warnings if "non-finite" not in w],  # n_unstable covers those
        # moved next to the bulk during the warm-up (--reinit-stragglers; 0 when off)
        "n_reinitialised": _reinitialised(run),
    }
    edge = prior_edge_mass(posterior.theta, problem.lower, problem.upper, labels=labels)
    return strag, edge


def simulation_summary(sim) -> dict:
    """The simulator's step and force convention for summary.json and the CLI output: backend,
    force interpolation, substeps, step (s) and how it was chosen (tolerance and estimated
    error of the displacement, m, when accuracy-controlled)."""
    info = dict(sim.step_info)
    return {
        "backend": sim.backend,
        "force_interp": sim.force_interp,
        "substeps": int(sim.substeps),
        "sim_dt_s": float(sim.sim_dt),
        "step_method": info.get("method"),
        "sim_tolerance_m": info.get("tolerance"),
        "estimated_error_m": info.get("estimated_error"),
        "max_sim_dt_s": info.get("max_sim_dt"),
    }


def simulation_line(sim) -> str:
    """One line for the CLI: the chosen step and its estimated error."""
    s = simulation_summary(sim)
    line = (
        f"simulation: {s['backend']} backend, forces {s['force_interp']} between samples, "
        f"{s['substeps']} substeps of {s['sim_dt_s'] * 1e3:.3g} ms"
    )
    if s["estimated_error_m"] is not None:
        line += (
            f" (estimated displacement error {s['estimated_error_m'] * 1e3:.3g} mm, "
            f"tolerance {s['sim_tolerance_m'] * 1e3:.3g} mm)"
        )
    return line


def _run_summary(problem, posterior, config, trace, fit, truth) -> dict:
    o = config["options"]
    from .figures import training_force_max

    kind, diag, warns = _diagnostics(
        o["sampler"], trace, list(problem.labels), o.get("mcmc_warmup", 0.5)
    )
    stable = np.asarray(fit["stable"], bool)
    strag, edge = _straggler_and_edge(problem, posterior)
    # modes the start pipeline's particles missed (treeinfer.inference.mode_check)
    missed = (getattr(posterior.run, "settings", None) or {}).get("missed_modes") or {}
    warns = [*warns, *strag["warnings"], *edge["warnings"], *missed.get("warnings", [])]
    summary = {
        "sampler": o["sampler"],
        "n_particles": o["particles"],
        "n_iterations": o["iterations"],
        "n_iterations_done": int(posterior.run.settings.get("n_iterations_done", o["iterations"])),
        "stop_reason": str(getattr(posterior.run, "stop_reason", "max_iterations")),
        "posterior_draws": {
            k: posterior.settings[k]
            for k in ("mcmc_draws", "dropped_stragglers", "n_dropped")
            if k in posterior.settings
        },
        "seed": o["seed"],
        "elapsed_s_sampling": trace["elapsed_s"],
        "diagnostics_kind": kind,
        "diagnostics": diag,
        "convergence_warnings": warns,
        "stragglers": strag,
        "prior_edge": edge,
        "n_unstable": int((~stable).sum()),
        "unstable_particles": np.flatnonzero(~stable).tolist(),
        "posterior": posterior_table(posterior.theta, problem.labels, stable),
        "level": LEVEL,
        "training_metrics": fit["metrics"],
        "simulation": simulation_summary(problem.sim),
        "training_force_max_N": training_force_max(problem),  # predictions beyond are refused
    }
    if problem.settings.get("integration_error"):  # the simulator's error as a noise floor
        summary["integration_error"] = problem.settings["integration_error"]
    model = getattr(problem, "model", None)
    if model is not None and (model.kind == "static" or not model.layout.infers_damping):
        from ..inference.static import damping_note

        summary["model_kind"] = model.kind
        summary["damping"] = damping_note(model.layout, model.kind)
    if problem.sim.model_report:  # a user's own URDF/MJCF: what was matched, set, repaired
        summary["model"] = problem.sim.model_report
    if truth is not None:
        from ..evaluation.metrics import posterior_vs_truth

        n_gains = len(truth)  # noise columns (sigma_x ...) have no true value
        if model is not None:  # stiffness only: theta holds Kp alone
            n_gains = min(n_gains, model.layout.dim)
        truth = np.asarray(truth, float)[:n_gains]
        chk = posterior_vs_truth(
            np.exp(np.asarray(posterior.theta, float)[:, :n_gains]), truth, LEVEL, stable, log=True
        )
        summary["truth"] = {
            lab: {
                "truth": float(truth[j]),
                "log_mean": float(chk.mean[j]),
                "log_truth": float(np.log(truth[j])),
                "in_interval": bool(chk.in_marginal[j]),
                "rel_error_log": float(chk.rel_error[j]),
            }
            for j, lab in enumerate(problem.labels[:n_gains])
        }
        summary["truth_in_joint_region"] = chk.in_joint
    return summary


# ==== the run folder ==============================================================================
def _csv_float(x) -> str:
    return repr(float(x))


def particles_csv(theta, labels, log_density, stable) -> str:
    """One row per particle.

    Columns: ``particle``, the labels in natural units, ``log_density``, ``stable``."""
    theta = np.asarray(theta, float)
    lines = [
        (
            f"# treeinfer {__version__}: posterior particles; Kp in {UNITS['Kp']}, Kd in "
            f"{UNITS['Kd']}; log_density of the whole target (-inf: unstable simulation)"
        ),
        ",".join(["particle", *labels, "log_density", "stable"]),
    ]
    from ..model.likelihood import natural_units

    for i, row in enumerate(natural_units(theta, labels)):
        lines.append(
            ",".join(
                [
                    str(i),
                    *(_csv_float(v) for v in row),
                    _csv_float(log_density[i]),
                    str(bool(stable[i])).lower(),
                ]
            )
        )
    return "\n".join(lines) + "\n"


def save_run(
    run_dir: str | os.PathLike,
    *,
    tree: Tree,
    config: dict,
    posterior,
    problem,
    trace: dict,
    fit: dict,
    summary: dict,
    truth=None,
    force: bool = False,
    inputs: Sequence[str | os.PathLike] = (),
    log=None,
    formats=("png",),
    figures=None,
) -> Path:
    """Write the run folder (see the module docstring) atomically: built in a staging folder,
    moved into place at the end. ``inputs`` (the tree file and data folder) are never replaced
    by ``force``; config.json records the checksums of the files written before it
    (``config["integrity"]``, see :mod:`treeinfer.runs.integrity`). ``formats``: the figures' file
    formats in ``plots/`` (``png``, ``pdf``, ``svg``). ``figures``: a
    :class:`~treeinfer.runs.figures.RunFigures` already drawing them (in ``formats``), else
    they are drawn here."""
    from ..inference.diagnostics import save_inference_data
    from .figures import run_inference_data, write_run_figures
    from .integrity import record_checksums

    labels = list(problem.labels)
    sampler = config["options"]["sampler"]
    stable = np.asarray(fit["stable"], bool)
    with staged_output_dir(run_dir, force, "run", inputs=inputs, log=log) as stage:
        dump_tree(tree, stage / "tree.yaml")
        attrs = {
            "treeinfer_version": __version__,
            "seed": int(config["options"]["seed"]),
            "n_iterations": int(config["options"]["iterations"]),
            "training_force_max_N": summary.get("training_force_max_N"),
        }
        # natural units with their units, the prior box, likelihood and noise model (issue 29)
        idata = run_inference_data(posterior, problem, trace, stable, summary, attrs)
        save_inference_data(idata, stage / "posterior.nc")
        atomic_write_text(
            stage / "particles.csv",
            particles_csv(posterior.theta, labels, posterior.log_density, stable),
        )
        arrays = {
            "positions": trace["positions"],
            "log_density": trace["log_density"],
            "iterations": trace["iterations"],
            "theta": np.asarray(posterior.theta),
            "final_log_density": np.asarray(posterior.log_density),
            "labels": np.asarray(labels),
            "diag_iterations": trace["diag_iterations"],
            **{f"diag_{k}": v for k, v in trace["diagnostics"].items()},
        }
        atomic_write_bytes(stage / "trace.npz", _npz_bytes(arrays))
        write_json(stage / "summary.json", summary)
        # written after the files it checksums: predict/evaluate/--resume verify them
        # "manifest": publishing adds manifest.json (every file): its absence is damage
        integrity = {**record_checksums(stage), "manifest": "manifest.json"}
        write_json(stage / "config.json", {**config, "integrity": integrity})

        if figures is not None:  # drawn on a second thread meanwhile (runs.figures)
            figures.write(stage / "plots", fit)
        else:
            write_run_figures(
                stage / "plots",
                posterior,
                problem,
                trace,
                stable,
                truth,
                fit,
                [f["name"] for f in config["data"]["files"]],
                sampler,
                bandwidth=run_bandwidths(trace, sampler),
                formats=formats,
            )
    return Path(run_dir)


class LoadedRun(NamedTuple):
    """A finished run, ready for :func:`predict_run` / :func:`evaluate_trajectories`.

    path: the run folder. tree: its tree. config: config.json. theta: [P, D] final particles
    (log Kp, log Kd; float32 as sampled). labels: theta's columns. log_density: [P].
    stable: [P] stable on the training data. sim: the simulator at the recorded obs_dt/substeps.
    kT: the likelihood temperature. summary: summary.json. grasp_fraction: where the training
    data were recorded (``--grasp-fraction`` of the run; None: the tree's grasp).
    """

    path: Path
    tree: Tree
    config: dict
    theta: np.ndarray
    labels: tuple[str, ...]
    log_density: np.ndarray
    stable: np.ndarray
    sim: Any
    kT: float
    summary: dict
    grasp_fraction: float | None
    notes: tuple[str, ...] = ()  # integrity notes (--allow-modified) to record in the output
    model: Any = (
        None  # treeinfer.inference.static.Model (static model or stiffness only); None: dynamic
    )


def load_run(
    run_dir: str | os.PathLike,
    cache: SimulatorCache | None = None,
    allow_modified: bool = False,
    model_file=None,
) -> LoadedRun:
    """Read a run folder written by :func:`save_run` (ConfigError naming what is missing).

    The files are checked against the checksums in config.json (:func:`treeinfer.runs.integrity.
    verify_run`): an edited tree.yaml or a damaged posterior is refused unless
    ``allow_modified``, which records notes in ``LoadedRun.notes`` instead. ``model_file``:
    where the run's own URDF/MJCF lies now (moved since the run); its sha256 must be the
    recorded one."""
    from ..io.manifest import read_manifest
    from ..io.safe_load import refuse_special_paths
    from .consistency import check_run_consistency
    from .integrity import load_npz, validate_run_config, validate_summary, verify_run

    run_dir = Path(run_dir)
    refuse_special_paths(run_dir, "run folder")  # a FIFO in it would block a reader
    if not run_dir.is_dir():
        part = partial_dir(run_dir)
        hint = f"; an interrupted run waits in {part} (--resume)" if part.is_dir() else ""
        raise ConfigError(f"{run_dir}: no such run folder{hint}")
    if not (run_dir / "config.json").is_file():
        raise ConfigError(f"{run_dir}: not a treeinfer run (no config.json); give infer's --out")
    notes = tuple(verify_run(run_dir, None, allow_modified))  # manifest first: config.json too
    config = read_json(run_dir / "config.json", "the run's config")
    if config.get("command") not in ("infer", "demo") or config.get("format") != RUN_FORMAT:
        raise ConfigError(
            f"{run_dir / 'config.json'}: not a treeinfer run config (command "
            f"{config.get('command')!r})"
        )
    validate_run_config(config, run_dir / "config.json")
    if read_manifest(run_dir) is None:  # a run from before manifests, or its manifest removed
        notes += tuple(verify_run(run_dir, config, allow_modified))
    for name in ("tree.yaml", "trace.npz"):
        if not (run_dir / name).is_file():
            raise ConfigError(f"{run_dir}: incomplete run folder, {name} is missing")
    tree = load_tree(run_dir / "tree.yaml")
    tree_file = tree  # before a moved model file is attached
    if model_file is not None:
        from ..tree.usermodel import attach_model

        tree = attach_model(tree, model_file, keep_sha256=True)
    z = load_npz(run_dir / "trace.npz", "trace file")
    try:
        theta, ld = z["theta"], z["final_log_density"]
        labels = tuple(str(s) for s in z["labels"])
    except KeyError as e:
        raise ConfigError(f"{run_dir / 'trace.npz'}: unreadable (no array {e})") from None
    from ..inference.static import model_for
    from ..model.likelihood import noise_columns

    model = model_for(tree, config.get("problem", {}).get("model_kind", "dynamic"))
    gains = list(model.labels)
    # observation channels' noise columns (sigma[name]) come last (treeinfer.model.channels)
    n_ch = int(config.get("problem", {}).get("channel_noise_columns", 0))
    if n_ch and not all(lab.startswith("sigma[") for lab in labels[len(labels) - n_ch :]):
        raise ConfigError(f"{run_dir}: trace.npz labels {list(labels)}: expected {n_ch} channel "
                          "noise columns sigma[name] last")  # fmt: skip
    noise_ok = list(labels[len(gains) : len(labels) - n_ch]) in (
        [list(noise_columns(k, True)) for k in ("gaussian", "ar1")]
        + [list(noise_columns("ar1", False)), []]
    )
    if list(labels[: len(gains)]) != gains or not noise_ok:
        raise ConfigError(
            f"{run_dir}: trace.npz labels {list(labels)} do not match tree.yaml "
            f"{list(model.labels)}"
        )
    if model.is_paper:
        model = None  # the paper's model of [log Kp, log Kd]
    has_summary = (run_dir / "summary.json").is_file()
    summary = read_json(run_dir / "summary.json", "the run's summary") if has_summary else {}
    validate_summary(summary, run_dir / "summary.json", len(theta))
    notes += tuple(
        check_run_consistency(run_dir, config, tree_file, theta, labels, summary, allow_modified)
    )
    stable = np.isfinite(ld)
    if summary.get("unstable_particles"):
        stable[np.asarray(summary["unstable_particles"], int)] = False
    p = config["problem"]
    # folders from before backends existed: auto; from before force interpolation: hold
    sim = simulator_for(
        tree,
        p["obs_dt"],
        p["substeps"],
        p.get("backend", "auto"),
        cache,
        force_interp=p.get("force_interp", "hold"),
    )
    if p.get("sim_step"):  # how the run's step was chosen (its estimated error), as recorded
        sim = dataclasses.replace(sim, step_info=dict(p["sim_step"]))
    return LoadedRun(
        run_dir,
        tree,
        config,
        theta,
        labels,
        ld,
        stable,
        sim,
        float(p["kT"]),
        summary,
        config["options"].get("grasp_fraction"),
        notes,
        model,
    )
