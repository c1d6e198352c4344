"""Summary, figures and markdown of the design study (``experiments/design_study.py``)."""

from __future__ import annotations

import numpy as np

from experiments.common import cpu_seconds

CONDITIONS = ("design", "design_target", "design_worst", "repeat", "random")
STAGES = ("first",) + CONDITIONS


# ==== summary =====================================================================================
def _quartiles(x) -> list[float]:
    return [float(v) for v in np.percentile(np.asarray(x, float), [25, 50, 75])]


def summarise(seeds: list[dict], labels) -> dict:
    """The study's figures from the per-seed records (conditions present in every record)."""
    conds = [c for c in CONDITIONS if all(c in r["stages"] for r in seeds)]
    stages = ["first"] + conds
    std = {s: np.array([r["stages"][s]["std"] for r in seeds]) for s in stages}  # [S, D]
    band = {s: np.array([r["stages"][s]["band_width_m"] for r in seeds]) for s in stages}
    worst = np.argmax(std["first"], axis=1)  # per seed: the worst-identified parameter after pull 1
    rows = np.arange(len(seeds))
    shrink = {c: std["first"][rows, worst] - std[c][rows, worst] for c in conds}
    ratio_std = {c: std[c][rows, worst] / std["first"][rows, worst] for c in conds}
    med = {c: float(np.median(shrink[c])) for c in conds}
    # the target: design's median shrink >= 2x repeat's (a repeat that shrinks nothing or widens
    # the std counts as 0, and the design must shrink it at all); the ratio is None then
    ratio = lambda c: med[c] / med["repeat"] if med["repeat"] > 0 else None
    met = lambda c: bool(med[c] > 0 and med[c] >= 2.0 * max(med["repeat"], 0.0))
    paired = {c: shrink[c] - shrink["repeat"] for c in conds if c != "repeat"}
    per_seed_2x = {
        c: int(np.sum((shrink[c] > 0) & (shrink[c] >= 2.0 * np.maximum(shrink["repeat"], 0.0))))
        for c in conds
        if c != "repeat"
    }
    wider = {
        c: [r["seed"] for r, a, b in zip(seeds, band[c], band["first"]) if a > b] for c in conds
    }
    out = {
        "labels": list(labels),
        "conditions": conds,
        "median_std": {s: np.median(v, 0).tolist() for s, v in std.items()},
        "worst_parameter_per_seed": [labels[i] for i in worst],
        "worst_std_shrink_per_seed": {c: shrink[c].tolist() for c in conds},
        "median_worst_std_shrink": med,
        "worst_std_shrink_quartiles": {c: _quartiles(shrink[c]) for c in conds},
        "worst_std_ratio_quartiles": {c: _quartiles(ratio_std[c]) for c in conds},
        "paired_shrink_minus_repeat_quartiles": {c: _quartiles(v) for c, v in paired.items()},
        "seeds_with_2x_repeat_shrink": per_seed_2x,
        "design_vs_repeat_shrink_ratio": ratio("design"),
        "target_2x_more_shrink_than_repeat": met("design"),
        "band_width_m_per_seed": {s: v.tolist() for s, v in band.items()},
        "median_band_width_m": {s: float(np.median(v)) for s, v in band.items()},
        "band_ratio_quartiles": {c: _quartiles(band[c] / band["first"]) for c in conds},
        "seeds_where_band_widens": wider,
        "design_never_widens_band": not wider["design"],
        "seeds_where_design_widens_band": wider["design"],
    }
    for c in ("design_worst", "design_target"):
        if c in conds:
            out[f"{c}_vs_repeat_shrink_ratio"] = ratio(c)
            out[f"{c}_target_2x"] = met(c)
            out[f"{c}_never_widens_band"] = not wider[c]
    if all("fisher_reference" in r for r in seeds):
        fr = lambda s, k: np.array([r["fisher_reference"][s][k] for r in seeds])
        out["median_crb_std"] = {s: np.median(fr(s, "crb_std"), 0).tolist() for s in stages}
        out["median_crb_band_m"] = {s: float(np.median(fr(s, "crb_band_m"))) for s in stages}
        out["median_std_over_crb"] = {
            s: np.median(std[s] / np.maximum(fr(s, "crb_std"), 1e-12), 0).tolist() for s in stages
        }
    if all("log_density_max_minus_median" in r["stages"]["first"] for r in seeds):
        out["median_log_density_max_minus_median"] = {
            s: float(np.median([r["stages"][s]["log_density_max_minus_median"] for r in seeds]))
            for s in stages
        }
    return out


def _figures(summary: dict, sugg):
    import matplotlib.pyplot as plt

    from treeinfer.design import plot_scores

    labels = summary["labels"]
    conds = summary.get("conditions", CONDITIONS)
    stages = ["first"] + list(conds)
    fig1, ax = plt.subplots(figsize=(1.4 * len(labels) + 3, 3.6))
    x = np.arange(len(labels))
    wbar = 0.8 / len(stages)
    for i, s in enumerate(stages):
        ax.bar(
            x + (i - (len(stages) - 1) / 2) * wbar,
            summary["median_std"][s],
            wbar,
            label="after pull 1" if s == "first" else f"+ {s}",
        )
    ax.set_xticks(x, labels, rotation=20)
    ax.set_ylabel("posterior std [log units] (median over seeds)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    fig1.tight_layout()
    fig2, ax2 = plt.subplots(figsize=(5, 3.6))
    bw = summary["band_width_m_per_seed"]
    for j in range(len(bw["first"])):
        ax2.plot(range(len(stages)), [1e3 * bw[s][j] for s in stages], "o-", color="0.6", lw=0.8)
    ax2.plot(
        range(len(stages)),
        [1e3 * summary["median_band_width_m"][s] for s in stages],
        "k*-",
        ms=10,
        label="median",
    )
    ax2.set_xticks(range(len(stages)), ["pull 1"] + [f"+{c}" for c in conds], rotation=15)
    ax2.set_ylabel("held-out 95% band width [mm]")
    ax2.set_yscale("log")
    ax2.legend()
    ax2.grid(alpha=0.3)
    fig2.tight_layout()
    fig3, _ = plot_scores(sugg)
    return {"std.png": fig1, "band.png": fig2, "scores_seed0.png": fig3}


def _ratio(r) -> str:
    return "n/a (the repeat's median shrink is <= 0)" if r is None else f"{r:.2f}"


def _q(q, scale=1.0, fmt=".3f") -> str:
    return f"{scale * q[1]:{fmt}} [{scale * q[0]:{fmt}}, {scale * q[2]:{fmt}}]"


def _stage_rows(conds, per_parameter: dict, rest) -> list[str]:
    """Markdown rows ``| stage | value per parameter | rest(stage) |``, pull 1 first."""
    rows = []
    for s in ["first"] + list(conds):
        name = "after pull 1" if s == "first" else f"+ {s}"
        cells = " | ".join(f"{v:.3f}" for v in per_parameter[s])
        rows.append(f"| {name} | {cells} | {rest(s)} |")
    return rows


def _markdown(cfg, summary: dict, seeds: list[dict], wall: float, cpu: float | None = None) -> str:
    labels = summary["labels"]
    conds = summary.get("conditions", CONDITIONS)
    n = len(seeds)
    init = (
        f"start: MAP + Laplace draws x{cfg.laplace_scale:g}"
        if cfg.init == "laplace"
        else "start: uniform in the prior box"
    )
    lr = (
        f"Adam step {cfg.learning_rate:g}"
        if cfg.final_learning_rate is None
        else f"Adam step {cfg.learning_rate:g} -> {cfg.final_learning_rate:g} (cosine)"
    )
    lines = [
        f"# Design study ({cfg.size}): which second pull?",
        "",
        (
            f"Tree `{cfg.tree}`, {n} seeds, displacement noise {cfg.noise_mm:g} mm, first pull: "
            f"ramp-hold-release {cfg.first_peak:g} N at the tip; NNSVGD {cfg.n_particles} "
            f"particles x {cfg.n_iterations} iterations ({init}; {lr}; the same for every arm); "
            f"candidates: grasp {list(cfg.grasp_fractions)} x peak {list(cfg.peak_forces)} N x "
            f"{list(cfg.profile_kinds)}; held-out: {cfg.heldout_peak:g} N hold at grasp "
            f"{cfg.heldout_grasp:g}. dt {cfg.dt:g} s, {cfg.duration:g} s pulls."
        ),
        "",
        "## Posterior std (log units), median over seeds",
        "",
        "| stage | " + " | ".join(labels) + " | held-out band [mm] |",
        "|---" * (len(labels) + 2) + "|",
    ]
    lines += _stage_rows(
        conds, summary["median_std"], lambda s: f"{1e3 * summary['median_band_width_m'][s]:.2f}"
    )
    if "median_crb_std" in summary:
        lines += [
            "",
            "Reference (Fisher information at the true parameters, Gaussian noise): median "
            "Cramér-Rao std, and the linearised held-out band; then the sampled std over it.",
            "",
            "| stage | " + " | ".join(labels) + " | lin. band [mm] | std / CRB (median) |",
            "|---" * (len(labels) + 3) + "|",
        ]
        lines += _stage_rows(
            conds,
            summary["median_crb_std"],
            lambda s: (
                f"{1e3 * summary['median_crb_band_m'][s]:.2f} | "
                + ", ".join(f"{v:.1f}" for v in summary["median_std_over_crb"][s])
            ),
        )
    if "median_log_density_max_minus_median" in summary:
        c = summary["median_log_density_max_minus_median"]
        lines += [
            "",
            "Convergence: best minus median particle log-density (nats, median over seeds; about "
            f"D/2 = {len(labels) / 2:g} when converged): "
            + ", ".join(f"{k} {v:.1f}" for k, v in c.items())
            + ".",
        ]
    q = summary["worst_std_shrink_quartiles"]
    qr = summary["worst_std_ratio_quartiles"]
    lines += [
        "",
        "## Targets",
        "",
        (
            "- Worst-identified parameter after pull 1 (per seed): "
            f"{', '.join(summary['worst_parameter_per_seed'])}."
        ),
        "- Shrink of its std (log units), median [25%, 75%] over seeds: "
        + "; ".join(f"{c} {_q(q[c])}" for c in conds)
        + ". Its std after / before: "
        + "; ".join(f"{c} {_q(qr[c], fmt='.2f')}" for c in conds)
        + ".",
        (
            "- design / repeat (ratio of the median shrinks) = "
            f"{_ratio(summary['design_vs_repeat_shrink_ratio'])} (target >= 2: "
            f"**{'met' if summary['target_2x_more_shrink_than_repeat'] else 'not met'}**). "
            "Per seed, the design arm's shrink minus the repeat's: "
            + "; ".join(
                f"{c} {_q(v)}" for c, v in summary["paired_shrink_minus_repeat_quartiles"].items()
            )
            + "; seeds where the arm shrinks it by > 0 and >= 2x the repeat's (a repeat <= 0 "
            "counting as 0): "
            + ", ".join(f"{c} {k}/{n}" for c, k in summary["seeds_with_2x_repeat_shrink"].items())
            + "."
        ),
        "- Held-out band after / before, median [25%, 75%]: "
        + "; ".join(f"{c} {_q(v, fmt='.2f')}" for c, v in summary["band_ratio_quartiles"].items())
        + ".",
        "- Never widens the held-out band: "
        + "; ".join(
            f"{c} **{'yes' if not w else 'no'}**" + (f" (wider at seeds {w})" if w else "")
            for c, w in summary["seeds_where_band_widens"].items()
        )
        + ".",
        "",
        "## Second pulls chosen",
        "",
        (
            "| seed | design (grasp, N, kind) | design_target | design_worst (parameter) | random "
            "| EIG of best [nats] | scoring [s] |"
        ),
        "|---|---|---|---|---|---|---|",
    ]

    def fmt(c):
        return f"{c['grasp_fraction']:g}, {c['peak_force']:g}, {c['profile_kind']}"

    for r in seeds:
        st = r["stages"]
        tgt = fmt(st["design_target"]["second_pull"]) if "design_target" in st else "-"
        lines.append(
            f"| {r['seed']} | {fmt(st['design']['second_pull'])} | {tgt} "
            f"| {fmt(st['design_worst']['second_pull'])} "
            f"({r['design_worst_parameter']}) | {fmt(st['random']['second_pull'])} | "
            f"{r['design_top5'][0]['score']:.2f} | {r['design_seconds']:.1f} |"
        )
    lines += [
        "",
        f"Wall time {wall:.0f} s, process CPU time {cpu_seconds() if cpu is None else cpu:.0f} s.",
        "",
    ]
    return "\n".join(lines)


def _suggestions_from_dict(d: dict):
    """A :class:`~treeinfer.design.Suggestions` back from its ``to_dict()`` (for the figure)."""
    from treeinfer.design import Candidate, Suggestions

    rows = d["candidates"]
    cands = tuple(
        Candidate(
            r["grasp_fraction"],
            r["peak_force"],
            r["profile_kind"],
            None if r["direction"] is None else tuple(r["direction"]),
        )
        for r in rows
    )
    num = lambda k: np.array([np.nan if r.get(k) is None else r[k] for r in rows], float)
    return Suggestions(
        cands,
        num("score"),
        num("stable_share"),
        None,
        None,
        tuple(r["spec"] for r in rows),
        d["settings"],
    )
