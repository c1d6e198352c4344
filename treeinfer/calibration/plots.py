"""SBC plots (rank histograms, expected coverage) and the output folder writer."""

from __future__ import annotations

import math

import numpy as np

from .stats import SBCResult, binomial_band, result_json


def plot_rank_histograms(result: SBCResult, path=None, band_level: float = 0.99, formats=None):
    """Rank histograms (one panel per parameter) with the ``band_level`` binomial band of a
    uniform histogram shaded; p-values in the titles. Returns the figure (saved to ``path``)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    d = len(result.labels)
    n = result.truth.shape[0]
    nb = result.uniformity["n_bins"]
    lo, hi = binomial_band(n, 1.0 / nb, band_level)
    ncol = min(d, 3)
    nrow = math.ceil(d / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.6 * ncol, 2.8 * nrow), squeeze=False)
    for j, lab in enumerate(result.labels):
        ax = axes[j // ncol][j % ncol]
        t = result.uniformity["parameters"][lab]
        ax.axhspan(lo, hi, color="0.85", label=f"{band_level:.0%} band (uniform)")
        ax.axhline(n / nb, color="0.5", lw=0.8)
        ax.bar(
            (np.arange(nb) + 0.5) / nb, t["counts"], width=1.0 / nb, color="C0", edgecolor="white"
        )
        ax.set_xlim(0, 1)
        ax.set_title(f"{lab}\np(chi2) {t['p_chi2']:.3g}, p(KS) {t['p_ks']:.3g}", fontsize=8)
        ax.set_xlabel(f"fractional rank (L = {result.n_draws})", fontsize=8)
        ax.set_ylabel("data sets", fontsize=8)
    for j in range(d, nrow * ncol):
        axes[j // ncol][j % ncol].axis("off")
    axes[0][0].legend(fontsize=7, loc="lower left")
    verdict = "PASS" if result.uniformity["pass"] else "FAIL"
    fig.suptitle(
        f"SBC rank histograms, N = {n}: {verdict} at {result.uniformity['alpha']:g} (Bonferroni)",
        fontsize=9,
    )
    fig.tight_layout()
    if path is not None:  # atomically, in each of ``formats`` (default: path's own suffix)
        from ..evaluation.plots import save_figure

        save_figure(fig, path, formats=formats)
        plt.close(fig)
    return fig


def plot_coverage(result: SBCResult, path=None, band_level: float = 0.99, formats=None):
    """Expected vs observed coverage of central intervals, one line per parameter, with the
    ``band_level`` binomial band of a calibrated posterior. Returns the figure."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    n = result.truth.shape[0]
    grid = np.linspace(0.01, 0.99, 99)
    lo = np.array([binomial_band(n, a, band_level)[0] for a in grid]) / n
    hi = np.array([binomial_band(n, a, band_level)[1] for a in grid]) / n
    fig, ax = plt.subplots(figsize=(4.2, 4.0))
    ax.fill_between(grid, lo, hi, color="0.85", label=f"{band_level:.0%} band (calibrated)")
    ax.plot([0, 1], [0, 1], color="0.4", lw=0.8)
    levels = np.asarray(result.levels)
    for j, lab in enumerate(result.labels):
        ax.plot(levels, result.coverage[:, j], "o-", ms=3, lw=1, label=lab)
    ax.set_xlabel("expected coverage (central interval level)")
    ax.set_ylabel("observed coverage")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.legend(fontsize=7)
    ax.set_title(f"SBC coverage, N = {n} data sets, L = {result.n_draws} draws", fontsize=9)
    fig.tight_layout()
    if path is not None:  # atomically, in each of ``formats`` (default: path's own suffix)
        from ..evaluation.plots import save_figure

        save_figure(fig, path, formats=formats)
        plt.close(fig)
    return fig


def write_outputs(result: SBCResult, directory, config: dict | None = None, formats=None) -> dict:
    """``sbc_summary.json``, ``ranks.csv``, ``draws.npz`` and ``plots/{rank_histograms,
    coverage}.png`` (or each of ``formats``: png, pdf, svg) into ``directory`` (atomic writes).
    Returns the summary dict."""
    from pathlib import Path

    from ..io.atomic import atomic_save, atomic_write_json, atomic_write_text

    directory = Path(directory)
    (directory / "plots").mkdir(parents=True, exist_ok=True)
    summary = result_json(result, config)
    atomic_write_json(directory / "sbc_summary.json", summary)
    lines = ["dataset," + ",".join(f"rank_{lab},truth_{lab}" for lab in result.labels)]
    for i in range(result.truth.shape[0]):
        cells = [str(i)]
        for j in range(len(result.labels)):
            cells += [str(int(result.ranks[i, j])), repr(float(result.truth[i, j]))]
        lines.append(",".join(cells))
    atomic_write_text(directory / "ranks.csv", "\n".join(lines) + "\n")
    with atomic_save(directory / "draws.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(
                fh,
                truth=result.truth,
                draws=result.draws,
                ranks=result.ranks,
                labels=np.asarray(result.labels),
            )
    plot_rank_histograms(result, directory / "plots" / "rank_histograms.png", formats=formats)
    plot_coverage(result, directory / "plots" / "coverage.png", formats=formats)
    return summary
