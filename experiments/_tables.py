"""Results records, markdown tables and the results writer of the studies (split from
:mod:`experiments.common`)."""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as `python experiments/<study>.py` from anywhere
    sys.path.insert(0, str(ROOT))

from experiments._config import Context, StudyConfig  # noqa: E402
from experiments._data import SyntheticData  # noqa: E402
from treeinfer.io.atomic import atomic_write_json, atomic_write_text, staged_output_dir


# ==== results =====================================================================================
def versions() -> dict:
    from treeinfer.runs import versions as run_versions

    v = run_versions(extended=True)
    v["mujoco-mjx"] = v.pop("mujoco_mjx")  # results.json spells it as the distribution does
    return v


def data_record(data: SyntheticData, problem) -> dict:
    return {
        "tree": data.tree.name,
        "grasp_branch": data.tree.grasp_branch,
        "train_grasp_fraction": data.tree.grasp_fraction,
        "true_params": data.true_params(),
        "train_profiles": list(data.train_specs),
        "test_profiles": list(data.test_specs),
        "test_grasp_fractions": [float(g) for g in data.test_grasp],
        "n_steps": int(data.train[0].n_steps),
        "dt_s": float(data.train[0].dt),
        "ground_truth": "plain MuJoCo C (float64), treeinfer.sim.reference.simulate_reference",
        "inference_simulator": {
            "engine": f"{problem.sim.backend} ({np.dtype(problem.sim.dtype).name})",
            "substeps": problem.sim.substeps,
            "sim_dt_s": problem.sim.sim_dt,
        },
        "problem": problem.settings,
    }


METRIC_NOTES = """\
Metric definitions (all on unseen test trajectories unless noted):

- **95% CI width** [m]: per test time step, the central 95% interval of a 1-D Gaussian KDE
  (Scott's rule) over the particles' predicted displacements
  (`treeinfer.evaluation.metrics.predictive_interval`);
  the width is averaged over all test points (trajectories x time steps).
- **% GT outside**: share of ground-truth test points outside that interval, in percent.
- **NLL / test point**: negative log density of each ground-truth test point under the same
  per-step KDE, averaged over points (nats; `treeinfer.evaluation.predictive_nll`). The total over
  all points is `predictive_nll` in results.json.
- **Posterior NLL (train)**: our reading of the paper's Table I "Nll of the estimated posterior
  from the training trajectories": minus the particle average of the Boltzmann log-likelihood
  `-sum_b L_b(theta) / kT` over the training trajectories (`treeinfer.evaluation.posterior_nll`);
  its scale depends on kT and on the number and length of the trajectories.
- **|log error|**: mean over the 2R parameters of |posterior mean of ln K - ln K_true|
  (0.1 is about 10% off); **in 95%**: how many true parameters lie inside the posterior's
  marginal 95% interval.
"""


def fmt(v, spec: str = ".3g") -> str:
    if v is None:
        return "n/a"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, float) and not math.isfinite(v):
        return "n/a"
    return format(v, spec)


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


METRIC_HEADERS = [
    "95% CI width [m]",
    "% GT outside",
    "NLL / test point",
    "posterior NLL (train)",
    "|log error|",
    "in 95%",
    "valid particles",
]


def metric_cells(m: dict) -> list[str]:
    if "error" in m:
        return ["failed"] * (len(METRIC_HEADERS) - 1) + [
            f"{m.get('n_valid_particles', 0)}/{m.get('n_particles', '?')}"
        ]
    return [
        fmt(m["ci_width"], ".3f"),
        fmt(m["pct_outside"], ".1f"),
        fmt(m["predictive_nll_per_point"], ".2f"),
        fmt(m.get("posterior_nll"), ".4g"),
        fmt(m.get("mean_abs_log_error"), ".2f"),
        f"{m.get('n_params_in_interval', 0)}/{m.get('n_params', 0)}",
        f"{m['n_valid_particles']}/{m['n_particles']}",
    ]


def parameter_table(
    conditions: Sequence[tuple[str, dict]], labels: Sequence[str], truth: np.ndarray
) -> str:
    """Posterior mean (and 95% interval) of each ln K per condition, truth in the first row."""
    rows = [["truth"] + [fmt(float(t), ".2f") for t in truth]]
    for name, m in conditions:
        if "parameters" not in m:
            rows.append([name] + ["n/a"] * len(labels))
            continue
        cells = []
        for lab in labels:
            p = m["parameters"][lab]
            mark = "" if p["in_interval"] else " *"
            cells.append(f"{p['mean']:.2f} [{p['lower']:.2f}, {p['upper']:.2f}]{mark}")
        rows.append([name] + cells)
    return (
        markdown_table(["ln K"] + list(labels), rows)
        + "\n\n(* truth outside the 95% marginal interval)"
    )


def config_line(cfg: StudyConfig, data: SyntheticData, problem, test: str | None = None) -> str:
    test = test or f"{len(data.test)} unseen test"
    return (
        f"size `{cfg.size}`: tree `{data.tree.name}` (R = {data.tree.n_inferred}), "
        f"{cfg.n_particles} particles, "
        f"{cfg.n_iterations} iterations, {len(data.train)} training and {test} "
        f"trajectories of {data.train[0].n_steps} samples at {cfg.dt:g} s, kT = {problem.kT:g}, "
        f"{problem.sim.backend} simulator, {problem.sim.substeps} substeps of "
        f"{problem.sim.sim_dt * 1e3:.3g} ms"
    )


def write_results(
    ctx: Context, record: dict, markdown: str, figures: dict[str, Any], t0: float
) -> Path:
    """Write ``results.json`` (record + config + seed + versions + wall time), ``results.md`` and
    the PNG figures into ``ctx.out`` atomically (a staged folder renamed into place)."""
    from treeinfer.evaluation import save_figure

    record = {
        "study": ctx.cfg.study,
        "size": ctx.cfg.size,
        "seed": ctx.seed,
        "config": ctx.cfg.to_dict(),
        "versions": versions(),
        "command": " ".join([Path(sys.argv[0]).name] + sys.argv[1:])
        if sys.argv and sys.argv[0]
        else None,
        **record,
        "figures": sorted(figures),
        "wall_time_s": time.perf_counter() - t0,
        "cpu_time_s": cpu_seconds(),
    }
    md = markdown + (
        f"\n\nWall time: {record['wall_time_s']:.0f} s, process CPU time "
        f"{record['cpu_time_s']:.0f} s "
        f"(seed {ctx.seed}; {record['versions'].get('jax_backend', '?')} backend).\n"
    )
    with staged_output_dir(ctx.out, force=True, what="results") as stage:
        for name, fig in figures.items():
            save_figure(fig, stage / name)
        atomic_write_json(stage / "results.json", record)
        atomic_write_text(stage / "results.md", md)
    return ctx.out


def cpu_seconds() -> float:
    """User + system CPU seconds of this process so far (all threads)."""
    import resource

    ru = resource.getrusage(resource.RUSAGE_SELF)
    return float(ru.ru_utime + ru.ru_stime)


def progress_bar(ctx: Context, total: int):
    from tqdm.auto import tqdm

    return tqdm(
        total=total,
        desc=ctx.cfg.study,
        unit="step",
        disable=not ctx.progress,
        position=None,
        leave=True,
    )
