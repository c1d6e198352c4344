"""``treeinfer.load_posterior(RUN)``: the :class:`treeinfer.inference.posterior.Posterior` of a run
folder, folders written before posterior.nc held natural units included (read from trace.npz)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..errors import PosteriorError
from ..inference.posterior import Posterior, PosteriorContext


def _theta_box(run) -> tuple[np.ndarray, np.ndarray]:
    """The prior box of a loaded run in theta units, NaN for the noise columns (their box is
    the likelihood's, not recorded)."""
    d = len(run.labels)
    if run.model is not None:
        lo, hi = (
            np.asarray(run.model.layout.lower, float),
            np.asarray(run.model.layout.upper, float),
        )
    else:
        blo, bhi = run.tree.bounds_array()
        lo, hi = np.log(blo), np.log(bhi)
    pad = np.full(d - len(lo), np.nan)
    return np.concatenate([lo, pad]), np.concatenate([hi, pad])


def _force_max(run) -> float | None:
    """N, the largest |force| of the run's training data: summary.json's record, else the data
    files named in config.json (older folders) when they are still there, else None."""
    v = run.summary.get("training_force_max_N")
    if isinstance(v, (int, float)) and math.isfinite(v) and v > 0:
        return float(v)
    from ..data.trajectories import read_trajectory

    data = run.config.get("data") or {}
    peak = 0.0
    try:
        for f in data.get("files", []):
            peak = max(
                peak, float(np.max(np.abs(read_trajectory(Path(data["dir"]) / f["name"]).force)))
            )
    except Exception:  # noqa: BLE001 - the data moved or changed: no force check, not an error
        return None
    return peak or None


def _truth(run) -> np.ndarray | None:
    """The true gains (natural units) of a simulation's run, from summary.json."""
    t = run.summary.get("truth")
    if not isinstance(t, dict) or not t:
        return None
    vals = []
    for lab in run.labels:
        if lab not in t:
            break
        vals.append(float(t[lab]["truth"]))
    return np.asarray(vals) if vals else None


def load_posterior(
    path, *, allow_poor_fit: bool = False, allow_modified: bool = False, cache=None
) -> Posterior:
    """The :class:`~treeinfer.inference.posterior.Posterior` of a run folder (``treeinfer infer
    --out RUN``, ``demo/run``).

    Checks the folder's checksums (``allow_modified`` accepts edited files, their notes in
    ``context.summary["integrity_notes"]``), refuses an interrupted run (``RUN.partial``: resume
    it first), and keeps a ``poor_fit`` run loadable for inspection (figures, ``to_arviz``,
    ``diagnostics``) while ``sample`` and the summaries refuse it unless ``allow_poor_fit``.
    ``cache``: a :class:`~treeinfer.runs.SimulatorCache` to share simulators between runs."""
    from ..model.gains import gains_from_theta
    from .checkpoint import PARTIAL_SUFFIX, partial_dir
    from .folder import load_run
    from .integrity import load_npz

    path = Path(path)
    if path.name.endswith(PARTIAL_SUFFIX) or (not path.exists() and partial_dir(path).is_dir()):
        run_dir = path.with_name(path.name.removesuffix(PARTIAL_SUFFIX))
        path = partial_dir(run_dir)
        raise PosteriorError(
            f"{path}: an interrupted run (a checkpoint, no posterior yet); continue it with "
            f"`treeinfer infer --resume {run_dir}` and load {run_dir}"
        )
    run = load_run(path, cache, allow_modified=allow_modified)
    z = load_npz(path / "trace.npz", "trace file")
    trace = {
        "positions": np.asarray(z["positions"]),
        "log_density": np.asarray(z["log_density"]),
        "iterations": np.asarray(z["iterations"]),
    }
    config, summary = run.config, run.summary
    settings = dict(config.get("posterior_settings") or {})
    settings.setdefault("sampler", config["options"]["sampler"])
    if summary.get("diagnostics_kind") == "importance":
        settings["sampler"] = "importance"
    theta = np.asarray(run.theta)
    if run.model is not None:
        kp, kd = run.model.layout.gains(theta)
    else:
        kp, kd = gains_from_theta(theta, run.tree.n_inferred)
    lower, upper = _theta_box(run)
    fit = summary.get("fit") or {}
    ctx = PosteriorContext(
        tree=run.tree,
        sim=run.sim,
        model=run.model,
        lower=lower,
        upper=upper,
        problem_settings=dict(config.get("problem") or {}),
        stable=np.asarray(run.stable, bool),
        truth=_truth(run),
        status=summary.get("status") or fit.get("status"),
        reasons=tuple(str(r) for r in fit.get("reasons", [])),
        path=path,
        trace=trace,
        summary={**summary, "integrity_notes": list(run.notes)} if run.notes else summary,
        force_max=_force_max(run),
        allow_poor_fit=bool(allow_poor_fit),
    )
    if run.grasp_fraction is not None:  # the run's --grasp-fraction: predictions default to it
        ctx = ctx._replace(
            problem_settings={**ctx.problem_settings, "grasp_fraction": run.grasp_fraction}
        )
    return Posterior(
        theta,
        np.asarray(kp),
        np.asarray(kd),
        np.asarray(run.log_density),
        tuple(run.labels),
        None,
        settings,
        ctx,
    )
