"""The on-the-spot check of an amortised posterior against the real simulator-based posterior,
on recordings inside and outside its training distribution (``experiments/
amortised_calibration.py --check N``).

In-distribution recordings are drawn as the training sets are (the truth from the training
prior, pulls of the layout's family, ``sigma_x`` from its range, the force clean in the
training share of them, else noisy in its range), simulated by the training simulator; each
goes through :func:`treeinfer.amortised.check.amortised_start` with the run's problem
(``make_problem``: the default Gaussian likelihood with the force-noise term, the box and the
inequality priors, on the same simulator). Out-of-distribution ones: forces ten times the
trained peaks (``force x10``), and the displacement 80 ms behind the force (``delay 80 ms``, a
logger's latency: inside every trained range, but no parameter set fits it)."""

from __future__ import annotations

import dataclasses
import time

import numpy as np

OOD_KINDS = ("force x10", "delay 80 ms")


def _recordings(am, tree, sim, n: int, seed: int, kind: str | None):
    """In-distribution recordings (:func:`treeinfer.amortised.simulations.
    simulate_recordings`), then made out-of-distribution as ``kind`` says."""
    from treeinfer.amortised.simulations import simulate_recordings

    cfg = am.config
    lay = cfg.layout
    if kind == "force x10":  # the pulls' forces ten times larger (and so the sag)
        lay = dataclasses.replace(lay, peak_range=tuple(10 * p for p in lay.peak_range))
    recs = simulate_recordings(tree, lay, cfg.train, n, seed, sim)
    if kind == "delay 80 ms":
        k = max(1, round(0.08 / lay.dt))
        recs = [
            (th, sf, [t._replace(displacement=_delayed(t.displacement, k)) for t in trajs])
            for th, sf, trajs in recs
        ]
    return recs


def _delayed(x, k: int):
    """``x`` ``k`` samples late (its first value held): a logger's latency. The noise moves
    with it, so the recording's own noise estimate is unchanged."""
    return np.concatenate([np.repeat(x[:1], k), x[:-k]])


def run_checks(
    am,
    tree,
    n: int,
    seed: int = 2000,
    particles: int = 64,
    log=print,
    budget_s: float | None = None,
) -> dict:
    """``{"rows": {"in": [...], kind: [...]}, "summary": {...}}``: per recording, whether the
    amortised answer was used, which check decided, k_hat, ESS, rounds, check seconds.

    The recordings run in turns (one in-distribution, one of each outside kind, then the next),
    so that ``budget_s`` (seconds; None: no limit), which stops starting new ones once spent,
    leaves every kind measured (``summary["stopped_at_budget"]``). A recording that fails the
    domain check gets no problem built (``make_problem``'s force-noise reference fit costs
    seconds to minutes and the start does not look at it)."""
    import treeinfer as ti
    from treeinfer.amortised import check
    from treeinfer.amortised.simulations import training_simulator

    sim = training_simulator(tree, am.config.layout, am.config.train.backend)
    kinds = (None, *OOD_KINDS)
    recs = {k: _recordings(am, tree, sim, n, seed + j, k) for j, k in enumerate(kinds)}
    rows = {"in": [], **{k: [] for k in OOD_KINDS}}
    t_start, stopped = time.perf_counter(), False
    for i in range(n):
        for kind in kinds:
            if i >= len(recs[kind]):
                continue
            if budget_s is not None and time.perf_counter() - t_start > budget_s:
                stopped = True
                break
            truth, sf, trajs = recs[kind][i]
            t0 = time.perf_counter()
            force, disp = am.check_recordings(trajs)
            start, report = check.amortised_start(am, force, disp)
            inside = not check.domain_reasons(am, am.features(force, disp))
            problem = ti.make_problem(tree, trajs, sim=sim) if inside else None
            t1 = time.perf_counter()
            post = start(problem, {"options": {"particles": particles, "seed": 0}}, lambda m: None)
            row = {
                "used": post is not None,
                "check": report.get("check"),
                "reason": report.get("reason", ""),
                "khat": report.get("khat"),
                "ess": report.get("ess"),
                "rounds": report.get("rounds"),
                "check_s": round(time.perf_counter() - t1, 3),
                "total_s": round(time.perf_counter() - t0, 3),
                "latency_ms": report["latency_ms"],
                "force_noise": sf,
            }
            if post is not None:  # the truth's place in the checked posterior, per column
                th = np.asarray(post.theta, float)
                row["z_truth"] = ((truth - th.mean(0)) / (th.std(0) + 1e-12)).round(2).tolist()
            rows["in" if kind is None else kind].append(row)
            log(f"{kind or 'in-distribution'} {i + 1}/{n}: {row}")
        if stopped:
            log(f"checks: time budget of {budget_s:g} s spent; stopped after {i} round(s)")
            break
    summary = {
        "in_used": f"{sum(r['used'] for r in rows['in'])}/{len(rows['in'])}",
        **{
            f"{k}_fell_back": f"{sum(not r['used'] for r in rows[k])}/{len(rows[k])}"
            for k in OOD_KINDS
        },
        "check_s_median_in": float(np.median([r["check_s"] for r in rows["in"]] or [np.nan])),
        "stopped_at_budget": stopped,
        "checks_s": round(time.perf_counter() - t_start, 1),
    }
    return {"rows": rows, "summary": summary, "particles": particles}


def checks_markdown(checks: dict) -> list[str]:
    s = checks["summary"]
    lines = [
        "## On-the-spot check against the simulator",
        "",
        f"In-distribution recordings answered without fallback: {s['in_used']} (median check "
        f"{s['check_s_median_in']:.2f} s, {checks['particles']} particles). Outside the "
        "training distribution, fell back: "
        + ", ".join(f"{k} {s[f'{k}_fell_back']}" for k in OOD_KINDS)
        + "."
        + (" Stopped at the time budget (--check-budget-s)." if s.get("stopped_at_budget") else ""),
        "",
        "| recordings | used | check | k_hat | ESS | rounds | check s |",
        "|---|---|---|---|---|---|---|",
    ]
    for kind, rows in checks["rows"].items():
        for r in rows:
            k = "" if r["khat"] is None else f"{r['khat']:.2f}"
            e = "" if r["ess"] is None else f"{r['ess']:.0f}"
            lines.append(
                f"| {kind} | {'yes' if r['used'] else 'no'} | {r['check']} | {k} | {e} | "
                f"{r['rounds'] or ''} | {r['check_s']:.2f} |"
            )
    return lines + [""]
