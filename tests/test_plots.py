"""Plots build the expected axes/artists and save non-empty PNGs."""

import matplotlib
import numpy as np
import pytest
from matplotlib.collections import PolyCollection

from treeinfer.errors import ConfigError
from treeinfer.evaluation import plots

matplotlib.use("Agg")  # the module itself never picks a backend


def _png_ok(path):
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


@pytest.fixture
def bands():
    rng = np.random.default_rng(0)
    t = np.linspace(0, 2, 50)
    mean = 0.1 * (1 - np.exp(-3 * t))
    w = 0.02 * t
    gt = mean + 0.01 * rng.normal(size=t.size)
    samples = mean + w * rng.normal(size=(8, t.size))
    return t, mean - w, mean + w, mean, gt, samples


def test_trajectory_bands(bands, tmp_path):
    t, lo, hi, mean, gt, samples = bands
    fig, ax = plots.plot_trajectory_bands(t, lo, hi, mean, gt, samples, title="pull 1")
    assert len(fig.axes) == 1
    assert len(ax.lines) == 8 + 2  # samples + mean + gt
    assert sum(isinstance(c, PolyCollection) for c in ax.collections) == 1
    gt_line = ax.lines[-1]
    assert matplotlib.colors.same_color(gt_line.get_color(), "tab:red")
    np.testing.assert_allclose(gt_line.get_ydata(), gt)
    assert ax.get_title() == "pull 1" and ax.get_ylabel() == "displacement [m]"
    plots.save_figure(fig, tmp_path / "band.png")
    _png_ok(tmp_path / "band.png")
    assert not list(tmp_path.glob(".*"))  # no temporary left behind
    with pytest.raises(ConfigError, match="lower/upper"):
        plots.plot_trajectory_bands(t, lo[:-1], hi, mean)


def test_band_grid_flat_and_rows(bands, tmp_path):
    t, lo, hi, mean, gt, samples = bands
    K = 5
    fig, axes = plots.plot_band_grid(
        t,
        np.tile(lo, (K, 1)),
        np.tile(hi, (K, 1)),
        np.tile(mean, (K, 1)),
        np.tile(gt, (K, 1)),
        titles=[f"sigma={s}" for s in range(K)],
        ncols=3,
        suptitle="noise sweep",
    )
    assert axes.shape == (2, 3)
    assert sum(ax.get_visible() for ax in axes.ravel()) == K
    assert axes[0, 1].get_title() == "sigma=1"
    assert axes[0, 0].get_legend() is not None and axes[0, 1].get_legend() is None
    plots.save_figure(fig, tmp_path / "grid.png")
    _png_ok(tmp_path / "grid.png")

    R, C = 2, 3
    tile = lambda a: np.broadcast_to(a, (R, C) + a.shape)
    fig, axes = plots.plot_band_grid(
        t,
        tile(lo),
        tile(hi),
        gt=tile(gt),
        samples=tile(samples),
        row_labels=["NNSVGD", "SVGD"],
        col_labels=["traj 1", "traj 2", "traj 3"],
    )
    assert axes.shape == (R, C) and all(ax.get_visible() for ax in axes.ravel())
    assert axes[1, 0].get_ylabel() == "SVGD" and axes[0, 2].get_title() == "traj 3"
    assert len(axes[1, 2].lines) == samples.shape[0] + 1
    with pytest.raises(ConfigError, match="gt"):
        plots.plot_band_grid(t, tile(lo), tile(hi), gt=np.tile(gt, (4, 1)))


def test_pair_plot_single_and_overlay(tmp_path):
    rng = np.random.default_rng(1)
    a = rng.multivariate_normal([1.0, 0.5, 2.0], np.diag([0.05, 0.01, 0.1]), size=300)
    b = rng.multivariate_normal([1.2, 0.4, 2.1], np.diag([0.2, 0.05, 0.3]), size=300)
    truth = np.array([1.0, 0.5, 2.0])
    labels = ["Kp[b1]", "Kd[b1]", "Kp[b2]"]
    fig, axes = plots.pair_plot(a, labels, truth)
    assert axes.shape == (3, 3)
    assert [ax.get_visible() for ax in axes.ravel()] == [
        True,
        False,
        False,
        True,
        True,
        False,
        True,
        True,
        True,
    ]
    assert axes[2, 0].get_xlabel() == "Kp[b1]" and axes[1, 0].get_ylabel() == "Kd[b1]"
    # truth: red dot in each lower panel at the true pair, red line on the diagonal
    dot = [ln for ln in axes[2, 1].lines if ln.get_marker() == "o"]
    assert len(dot) == 1 and (dot[0].get_xdata()[0], dot[0].get_ydata()[0]) == (0.5, 2.0)
    assert any(np.allclose(ln.get_xdata(), 1.0) for ln in axes[0, 0].lines)
    assert len(axes[1, 0].collections) == 1  # scatter
    plots.save_figure(fig, tmp_path / "pair.png")
    _png_ok(tmp_path / "pair.png")

    fig, axes = plots.pair_plot({"NNSVGD": a, "SVGD": b}, labels, truth, kind="kde")
    assert len(fig.legends) == 1
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["NNSVGD", "SVGD", "truth"]
    assert len(axes[1, 0].collections) >= 2  # contour sets, one per sample set
    plots.save_figure(fig, tmp_path / "pair_overlay.png")
    _png_ok(tmp_path / "pair_overlay.png")


def test_pair_plot_collapsed_set_falls_back():
    x = np.tile([1.0, 2.0], (20, 1))
    _fig, axes = plots.pair_plot(x, ["a", "b"], kind="kde")
    assert len(axes[1, 0].collections) == 1  # scatter instead of contours
    with pytest.raises(ConfigError, match="labels"):
        plots.pair_plot(x, ["a"])


def test_metric_bars(tmp_path):
    names = ["0.0", "0.05", "0.1", "0.2"]
    vals = {"CI width [m]": [0.05, 0.06, 0.08, 0.12], "% GT outside": [1.0, 2.0, 4.0, 9.0]}
    fig, ax = plots.metric_bars(names, vals, title="noise", separate=False)
    assert len(ax.patches) == 8 and len(ax.containers) == 2
    assert [t.get_text() for t in ax.get_xticklabels()] == names
    plots.save_figure(fig, tmp_path / "bars.png")
    _png_ok(tmp_path / "bars.png")
    # default: scales differ ~75-fold -> one panel per metric
    fig, axes = plots.metric_bars(names, vals, title="noise")
    assert len(axes) == 2 and axes[1].get_title() == "% GT outside"
    np.testing.assert_allclose([p.get_height() for p in axes[0].patches], vals["CI width [m]"])
    plots.save_figure(fig, tmp_path / "bars_separate.png")
    _png_ok(tmp_path / "bars_separate.png")
    fig, ax = plots.metric_bars(
        names, {"NNSVGD": [0.1, 0.2, 0.3, 0.4], "SVGD": [0.2, 0.3, 0.4, 0.5]}
    )
    assert len(ax.patches) == 8
    with pytest.raises(ConfigError, match="one per condition"):
        plots.metric_bars(names, {"x": [1.0, 2.0]})


def test_plot_trace(tmp_path):
    rng = np.random.default_rng(2)
    n, P = 100, 16
    ld = -100 * np.exp(-np.arange(n) / 20)[:, None] - rng.random((n, P))
    ld[50:, 3] = -np.inf  # an unstable particle
    fig, axes = plots.plot_trace(ld, bandwidth=np.geomspace(1.0, 0.1, n))
    assert len(axes) == 2
    mean_line = axes[0].lines[0]
    expected = np.array([row[np.isfinite(row)].mean() for row in ld])
    np.testing.assert_allclose(mean_line.get_ydata(), expected)
    assert len(fig.axes) == 3  # + twin axis for the % non-finite
    plots.save_figure(fig, tmp_path / "trace.png")
    _png_ok(tmp_path / "trace.png")
    fig, axes = plots.plot_trace(ld[:, [0, 1]])
    assert len(axes) == 1 and len(fig.axes) == 1
