"""The tables of ``experiments/mangrove.py`` (results.md): the headline per test and channel,
the per-part table and the posterior summaries; and its figure of the bands."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

PARTS = ("ramp2", "hold", "release")


def _deg(x: float) -> str:
    return f"{math.degrees(x):.4f}"


def summary_lines(results: list[dict]) -> list[str]:
    """The headline table: per test and channel, the held-out coverage (ramp2 + release; the
    hold apart) and RMSE of each model fitted on every test, against the beam's RMSE."""
    tests = list(dict.fromkeys(r["test"] for r in results))
    by = {(r["test"], r["model"]): r for r in results}
    kinds = [
        k for k in dict.fromkeys(r["model"] for r in results) if all((t, k) in by for t in tests)
    ]
    lines = [
        "| test | channel | "
        + " | ".join(f"{k}: held-out cov. / RMSE" for k in kinds)
        + " | RMSE beam |",
        "|---|---|" + "---|" * len(kinds) + "---|",
    ]
    for t in tests:
        first = by[(t, kinds[0])] if kinds else next(r for r in results if r["test"] == t)
        for c in first["parts"]["heldout"]:
            cells = [
                f"{by[(t, k)]['parts']['heldout'][c]['coverage']:.0%} / "
                f"{_deg(by[(t, k)]['parts']['heldout'][c]['rmse_chain'])}"
                for k in kinds
            ]
            h = first["parts"]["heldout"][c]
            lines.append(f"| {t} | {c} | " + " | ".join(cells) + f" | {_deg(h['rmse_beam'])} |")
    return lines


def long_lines(results: list[dict]) -> list[str]:
    """Every fit (also those run on some tests only): held-out and hold coverage, RMSE, the
    residual check, against the baselines."""
    lines = [
        "| test | channel | model | held-out cov. | hold cov. | RMSE (deg) | band width (deg) "
        "| lag-1 | RMSE beam | RMSE springs |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    tests = list(dict.fromkeys(r["test"] for r in results))
    for t in tests:
        rows = [r for r in results if r["test"] == t]
        for c in rows[0]["parts"]["heldout"]:
            for r in rows:
                h, hold = r["parts"]["heldout"][c], r["parts"]["hold"][c]
                lag = f"{r['residual_lag1'][c]:.2f}"
                if r.get("innovations_lag1"):
                    lag += f" ({r['innovations_lag1'][c]:.2f})"
                width = _deg(h["band_width"]) if "band_width" in h else "-"
                lines.append(
                    f"| {t} | {c} | {r['model']} | {h['coverage']:.0%} | {hold['coverage']:.0%} "
                    f"| {_deg(h['rmse_chain'])} | {width} | {lag} | {_deg(h['rmse_beam'])} "
                    f"| {_deg(h['rmse_springs'])} |"
                )
    return lines


def markdown(results: list[dict], config: dict) -> str:
    lines = [
        "# Mangrove static pulling tests: chain models, a softening root plate, correlated noise",
        "",
        f"Data: Hill et al. (2024), doi:10.1016/j.ecoleng.2024.107259 ({config['data']}).",
        *(
            [
                "Fit: the whole loading (ramp and hold). Held out: the release (`heldout`).",
            ]
            if config.get("split") == "loading"
            else [
                "Fit: first half of the loading ramp. Held out: the second half of the ramp",
                "(ramp2), the hold at the peak (hold) and the release (release); `heldout` =",
                "ramp2 + release.",
            ]
        ),
        "Coverage: share of recorded tilts inside the chain's 95% posterior predictive band.",
        "RMSE in degrees: the chain's predictive mean and two baselines fitted by least squares",
        "to the same data: beam (a uniform Euler-Bernoulli cantilever on a root-plate spring,",
        "one pair of compliances for both inclinometers) and springs (tilt = moment at the",
        "ground / K_c, one K_c per inclinometer). lag-1: the lag-1 autocorrelation of the",
        "residuals on the fitted samples (the check: above 0.3, i.i.d. noise is the wrong model);",
        "in brackets for +ar1 and +ar1+gain fits, of the standardised Kalman innovations (above",
        "0.3, the noise model does not account for the correlation either).",
        "Models: elastic (springs), creep (a standard linear solid per joint), +ar1 (AR(1)",
        "residuals in continuous time, correlation time <= 5 s, inferred jointly), lag+ (a",
        "fast lag element on the root joint, 0.05-5 s, the slow creep then 5-1000 s), lag2+",
        "(the fast lag on every joint), soft+ (a softening root plate: rotation (M/K)(1 +",
        "M/(K theta_s)), theta_s 0.25-25 deg), /dq (driven by the force through the load",
        "cell's 10 N level crossings, `dequantised_force`, instead of the recorded staircase),",
        "+gain (and a gain error per channel: model error proportional to the tilt, an OU",
        "process with correlation time 5-50 s, `treeinfer.inference.pulltest.gain`; its band",
        "by the gain's stationary marginal unless the config says gain_band forecast), /hist",
        "(driven from the record's start, the pre-load not fitted: `--history`).",
        "The first table: the models fitted on all four tests (beam RMSE: on the recorded",
        "force); the second: every fit, each with its own baselines and (where recorded) the",
        "band's mean width on the held-out samples (its sharpness: a wide band covers anything).",
        "",
        f"Command: `{config['command']}`",
        "",
        *summary_lines(results),
        "",
        *long_lines(results),
        "",
        "| test | model | channel | part | n | coverage | RMSE chain (deg) | RMSE beam (deg) "
        "| RMSE springs (deg) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        for part in ("fit", *PARTS, "heldout"):
            for c, m in r["parts"][part].items():
                lines.append(
                    f"| {r['test']} | {r['model']} | {c} | {part} | {m['n']} | "
                    f"{m['coverage']:.1%} | {_deg(m['rmse_chain'])} | {_deg(m['rmse_beam'])} | "
                    f"{_deg(m['rmse_springs'])} |"
                )
    lines += [
        "",
        "| test | model | Kp root (N m/rad) | Kp stem (N m/rad) | creep ratio root / stem "
        "| creep tau root / stem (s) | lag ratio / tau root (s) | lag ratio / tau stem (s) "
        "| theta_s root (deg) | sigma root (deg) "
        "| sigma trunk (deg) | AR(1) tau (s) "
        "| R-hat max | divergences | beam K (N m/rad) | beam EI (N m^2) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        p, d = r["posterior"], r["diagnostics"]
        # per-joint or per-channel lists; a scalar parameter's (the root's lag) a number
        rh = [v for k in d if k.startswith("r_hat") for v in np.atleast_1d(d[k] or [])]

        def ci(k, scale=1.0):
            if k not in p:
                return "-"
            m, lo, hi = (p[k][q] * scale for q in ("mean", "q2.5", "q97.5"))
            return f"{m:.4g} [{lo:.4g}, {hi:.4g}]"

        lines.append(
            f"| {r['test']} | {r['model']} | {ci('kp_root')} | {ci('kp_stem')} | "
            f"{ci('creep_ratio_root')} / {ci('creep_ratio_stem')} | "
            f"{ci('creep_tau_root')} / {ci('creep_tau_stem')} | "
            f"{ci('lag_ratio_root')} / {ci('lag_tau_root')} | "
            f"{ci('lag_ratio_stem')} / {ci('lag_tau_stem')} | "
            f"{ci('soft_tilt_root', 180 / math.pi)} | "
            f"{ci('sigma_root', 180 / math.pi)} | {ci('sigma_trunk', 180 / math.pi)} | "
            f"{ci('tau_ar_root')} / {ci('tau_ar_trunk')} | "
            f"{max(rh) if rh else float('nan'):.3f} | {d['divergences']} | "
            f"{r['beam']['k_root']:.4g} | {r['beam']['ei']:.4g} |"
        )
    lines += ["", "Config:", "", "```json", json.dumps(config, indent=2), "```", ""]
    return "\n".join(lines)


def figure(curves: dict[str, dict], path: Path, kind: str = "elastic") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(curves)
    fig, axs = plt.subplots(len(names), 2, figsize=(13, 2.9 * len(names)), squeeze=False)
    for r, name in enumerate(names):
        cv = curves[name]
        t = cv["time"]
        for i, c in enumerate(cv["channels"]):
            ax = axs[r, i]
            deg = np.rad2deg
            ax.axvspan(*cv["fit"], color="0.9", label="fitted")
            ax.plot(t, deg(cv["tilt"][i]), ".", ms=1.5, color="0.3", label="recorded")
            ax.fill_between(
                t,
                deg(cv["band"]["lo"][i]),
                deg(cv["band"]["hi"][i]),
                color="C0",
                alpha=0.35,
                label=f"chain ({kind}): 95% predictive band",
            )
            ax.plot(t, deg(cv["band"]["mean"][i]), color="C0", lw=0.8)
            ax.plot(t, deg(cv["beam"][i]), "--", color="C3", lw=0.8, label="beam baseline")
            ax.plot(t, deg(cv["springs"][i]), ":", color="C2", lw=0.9, label="spring baseline")
            for k in ("ramp_end", "release_start"):
                ax.axvline(cv["phases"][k], color="0.5", lw=0.5)
            ax.set_title(f"{name}: {c} inclinometer", fontsize=9)
            ax.set_ylabel("tilt along the pull (deg)")
            if r == len(names) - 1:
                ax.set_xlabel("time (s)")
            if r == 0 and i == 0:
                ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
