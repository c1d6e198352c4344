"""The study scripts (``experiments/<study>.py``) end to end at ``--size tiny``, plus their data.

The scripts run in this process through ``main(argv)`` with one posterior cache for the module, as
they would in sequence from the shell: the NN-prior, noise (sigma = 0) and grasp studies reuse the
baselines' posteriors, so MJX compiles three sampler programs (NNSVGD, SVGD, noisy NNSVGD) and
two prediction programs in all. Cold, on a loaded 2-core machine, that is several minutes; with
the persistent compilation cache warm, well under a minute or two.

The data tests need no MJX: ground truth comes from plain MuJoCo.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from experiments import baselines, grasp, nn_prior, noise
from experiments import common as C

ROOT = Path(__file__).resolve().parents[1]
PNG = b"\x89PNG\r\n\x1a\n"
METRIC_KEYS = {
    "ci_width",
    "pct_outside",
    "fraction_outside",
    "predictive_nll",
    "predictive_nll_per_point",
    "posterior_nll",
    "parameters",
    "mean_abs_log_error",
    "n_params_in_interval",
    "n_valid_particles",
    "n_particles",
    "n_test_trajectories",
}


# ---- data (no MJX) -------------------------------------------------------------------------------
def test_data_is_seeded_and_train_test_differ():
    cfg = C.study_config("baselines", "tiny")
    a, b, other = C.make_data(cfg, 0), C.make_data(cfg, 0), C.make_data(cfg, 1)
    assert a.train_specs == b.train_specs and a.test_specs == b.test_specs
    for x, y in zip(a.train + a.test, b.train + b.test):
        np.testing.assert_array_equal(x.displacement, y.displacement)
    np.testing.assert_array_equal(a.theta, b.theta)
    assert not np.allclose(a.theta, other.theta)
    assert not set(a.train_specs) & set(a.test_specs)  # unseen test profiles
    assert len(a.train) == cfg.n_train and len(a.test) == cfg.n_test
    # true parameters: parent at least as stiff and as damped as its child (inequality prior's
    # premise)
    tree = a.tree
    for parent, child in tree.inferred_pairs():
        assert a.kp[parent] >= a.kp[child] and a.kd[parent] >= a.kd[child]
    lo, hi = tree.bounds_array()
    assert np.all(np.exp(a.theta) > lo) and np.all(np.exp(a.theta) < hi)


def test_ground_truth_pulls_down_and_matches_the_recorded_force():
    from treeinfer.data.forces import from_spec

    cfg = C.study_config("baselines", "tiny")
    data = C.make_data(cfg, 0)
    for traj, spec in zip(data.train, data.train_specs):
        np.testing.assert_array_equal(traj.force, from_spec(spec, cfg.duration, cfg.dt))
        assert traj.displacement[0] == pytest.approx(0.0, abs=1e-9)  # settled rest at t = 0
        assert traj.displacement.max() > 1e-3  # a downward pull moves the grasp point down
        np.testing.assert_allclose(traj.time, np.arange(traj.n_steps) * cfg.dt)


def test_grasp_test_set_repeats_profiles_at_each_location():
    cfg = C.study_config("grasp", "tiny")
    data = C.make_data(cfg, 0)
    k = cfg.n_test_per_location
    assert (
        len(data.test) == k * len(cfg.grasp_locations) == cfg.n_test
    )  # same prediction shape as the others
    np.testing.assert_array_equal(data.test_grasp, np.repeat(cfg.grasp_locations, k))
    for i in range(k):
        same = [data.test[j * k + i] for j in range(len(cfg.grasp_locations))]
        for t in same[1:]:
            np.testing.assert_array_equal(t.force, same[0].force)
        # the same downward force moves a point nearer the joint less (shorter lever, smaller
        # torque)
        peaks = [np.max(t.displacement) for t in same]
        assert np.all(np.diff(peaks) > 0), peaks


def test_relative_noise_has_the_documented_sigma():
    cfg = C.study_config("noise", "tiny")
    clean = C.make_data(cfg, 0)
    level = 0.05
    noisy, info = C.add_relative_noise(clean, level, seed=0)
    trajs = clean.train + clean.test
    f_peak = max(np.abs(t.force).max() for t in trajs)
    x_peak = max(np.abs(t.displacement).max() for t in trajs)
    assert info["sigma_force_N"] == pytest.approx(level * f_peak)
    assert info["sigma_displacement_m"] == pytest.approx(level * x_peak)
    df = np.concatenate([n.force - c.force for n, c in zip(noisy.train + noisy.test, trajs)])
    dx = np.concatenate(
        [n.displacement - c.displacement for n, c in zip(noisy.train + noisy.test, trajs)]
    )
    # sample std of n ~ 100 Gaussian draws: within 30% of sigma with overwhelming probability
    assert np.std(df) == pytest.approx(info["sigma_force_N"], rel=0.3)
    assert np.std(dx) == pytest.approx(info["sigma_displacement_m"], rel=0.3)
    assert all(
        t.velocity is None for t in noisy.train
    )  # differentiated from the noisy displacement
    again, _ = C.add_relative_noise(clean, level, seed=0)
    np.testing.assert_array_equal(again.train[0].force, noisy.train[0].force)
    same, zero = C.add_relative_noise(clean, 0.0, seed=0)
    assert same is clean and zero["sigma_force_N"] == 0.0


def test_config_sizes_and_errors():
    full = C.study_config("nn_prior", "full")
    assert (full.n_particles, full.n_test, full.n_train) == (128, 25, 5)
    assert C.study_config("baselines", "cpu").samplers == C.ALL_SAMPLERS
    assert C.study_config("baselines", "cpu").tree == "three_branch"
    with pytest.raises(C.ConfigError, match="samplers"):
        C.study_config("baselines", "tiny", samplers=("hmc",))
    with pytest.raises(C.ConfigError, match="--size"):
        C.study_config("baselines", "huge")
    with pytest.raises(C.ConfigError, match="grasp locations"):
        C.study_config("grasp", "tiny", grasp_locations=(0.0, 1.0))


def test_config_likelihood_options():
    """--likelihood / --noise-displacement reach every study's config (issue 11), checked."""
    assert C.study_config("baselines", "tiny").likelihood == "boltzmann"
    cfg = C.study_config("noise", "tiny", likelihood="gaussian", noise_displacement=0.002)
    assert (cfg.likelihood, cfg.noise_displacement) == ("gaussian", 0.002)
    with pytest.raises(C.ConfigError, match="likelihood"):
        C.study_config("baselines", "tiny", likelihood="cauchy")
    with pytest.raises(C.ConfigError, match="noise_displacement"):
        C.study_config("baselines", "tiny", likelihood="gaussian", noise_displacement=-1.0)
    args = C.build_parser("baselines", "d").parse_args(
        ["--likelihood", "student_t", "--noise-displacement", "0.001", "--no-cache"]
    )
    assert (args.likelihood, args.noise_displacement) == ("student_t", 0.001)


# ---- command line --------------------------------------------------------------------------------
@pytest.mark.parametrize("module", [baselines, nn_prior, noise, grasp])
def test_help(module, capsys):
    with pytest.raises(SystemExit) as e:
        module.main(["--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    assert "--size {tiny,cpu,full}" in text and "--out" in text and "--seed" in text


def test_script_runs_from_the_shell():
    out = subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "grasp.py"), "--help"],
        check=False,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert "--locations" in out.stdout


def test_refuses_a_folder_of_other_files(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("mine")
    rc = grasp.main(["--size", "tiny", "--out", str(tmp_path), "--quiet"])
    assert rc == 2
    assert "no results.json" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


# ---- the studies at --size tiny ------------------------------------------------------------------
@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("posteriors")


def run_study(module, out: Path, cache: Path, *extra: str) -> dict:
    rc = module.main(
        ["--size", "tiny", "--out", str(out), "--cache", str(cache), "--quiet", *extra]
    )
    assert rc == 0
    return json.loads((out / "results.json").read_text())


def check_folder(r: dict, out: Path, study: str, figures: set[str], n_conditions: int) -> None:
    assert r["study"] == study and r["size"] == "tiny" and r["seed"] == 0
    assert r["config"]["study"] == study and r["config"]["size"] == "tiny"
    assert {"jax", "mujoco", "mujoco-mjx", "treeinfer", "python"} <= set(r["versions"])
    assert r["wall_time_s"] > 0
    assert figures <= set(r["figures"])
    for name in r["figures"]:
        assert (out / name).read_bytes()[:8] == PNG, name
    md = (out / "results.md").read_text()
    assert md.startswith("# ") and "|---|" in md
    tp = r["data"]["true_params"]
    assert len(tp["theta_log"]) == len(tp["labels"]) == 2 * len(tp["kp"])
    assert len(r["conditions"]) == n_conditions
    for c in r["conditions"]:
        assert c["name"] in md
        m = c["metrics"]
        assert METRIC_KEYS <= set(m), sorted(METRIC_KEYS - set(m))
        assert m["ci_width"] > 0 and 0 <= m["pct_outside"] <= 100
        assert set(m["parameters"]) == set(tp["labels"])


@pytest.fixture(scope="module")
def baseline_run(tmp_path_factory, cache):
    out = tmp_path_factory.mktemp("baselines")
    return out, run_study(baselines, out, cache, "--samplers", "nnsvgd,svgd")


@pytest.mark.slow  # a study script end to end (several minutes cold)
def test_baselines(baseline_run):
    out, r = baseline_run
    check_folder(
        r,
        out,
        "baselines",
        {"bands.png", "metrics.png", "pairs.png", "trace_nnsvgd.png", "trace_svgd.png"},
        2,
    )
    assert [c["sampler"] for c in r["conditions"]] == ["nnsvgd", "svgd"]
    assert [c["nn_prior"] for c in r["conditions"]] == [True, False]
    inf = r["conditions"][0]["inference"]
    assert inf["n_particles"] == 6 and inf["n_iterations"] == 3 and not inf["from_cache"]


@pytest.mark.slow  # a study script end to end (several minutes cold)
def test_nn_prior_reuses_the_baselines_posteriors(baseline_run, tmp_path, cache):
    r = run_study(nn_prior, tmp_path, cache)
    check_folder(r, tmp_path, "nn_prior", {"pairs.png", "bands.png", "metrics.png"}, 2)
    assert set(r["paper_table_I"]) == {"NNSVGD", "SVGD"}
    base = {c["name"]: c for c in baseline_run[1]["conditions"]}
    for c in r["conditions"]:
        assert c["inference"]["from_cache"]
        assert c["inference"]["cache_key"] == base[c["name"]]["inference"]["cache_key"]
        # same posterior, same data: the same numbers
        assert c["metrics"]["ci_width"] == base[c["name"]]["metrics"]["ci_width"]
        assert c["metrics"]["posterior_nll"] == base[c["name"]]["metrics"]["posterior_nll"]


@pytest.mark.slow  # a study script end to end (several minutes cold)
def test_noise(baseline_run, tmp_path, cache):
    r = run_study(noise, tmp_path, cache)
    check_folder(r, tmp_path, "noise", {"bands.png", "metrics.png"}, 2)
    zero, noisy = r["conditions"]
    assert (
        zero["noise"]["sigma_force_N"] == 0 and zero["inference"]["from_cache"]
    )  # the clean NNSVGD
    assert noisy["noise"]["level"] == 0.05 and noisy["noise"]["sigma_force_N"] > 0
    assert not noisy["inference"]["from_cache"]
    assert "sigma_F" in (tmp_path / "results.md").read_text()
    assert noisy["metrics_vs_clean_truth"]["ci_width"] == noisy["metrics"]["ci_width"]  # same bands


@pytest.mark.slow  # a study script end to end (several minutes cold)
def test_grasp_and_seed_reproducibility(baseline_run, tmp_path, cache):
    r = run_study(grasp, tmp_path / "a", cache)
    check_folder(r, tmp_path / "a", "grasp", {"bands.png", "metrics.png"}, 4)
    assert [c["grasp_fraction"] for c in r["conditions"]] == [0.25, 0.5, 0.75, 1.0]
    assert r["inference"]["from_cache"]
    assert all(c["metrics"]["n_test_trajectories"] == 1 for c in r["conditions"])
    # the same seed without the posterior cache: the sampler runs again and gives the same numbers
    again = run_study(grasp, tmp_path / "b", cache, "--no-cache")
    assert not again["inference"]["from_cache"]
    for c1, c2 in zip(r["conditions"], again["conditions"]):
        assert c1["metrics"]["ci_width"] == c2["metrics"]["ci_width"]
        assert c1["metrics"]["parameters"] == c2["metrics"]["parameters"]


@pytest.mark.slow  # a study script end to end (several minutes cold)
def test_design_study_tiny(tmp_path):
    """experiments/design_study.py end to end at --size tiny: every arm of every seed gets a
    posterior and a held-out band, the summary states each target, and --resummarise rebuilds
    the same markdown from results.json (the program cache is the caller's: both stages and
    both seeds run on one batched MAP program and one batched sampler program)."""
    from experiments import design_study
    from treeinfer.sim.program_cache import ProgramCache

    out = tmp_path / "design"
    programs = ProgramCache()
    assert design_study.main(["--size", "tiny", "--out", str(out), "--quiet"], programs) == 0
    res = json.loads((out / "results.json").read_text())
    assert len(res["seeds"]) == 2 and res["config"]
    for seed in res["seeds"]:
        assert set(seed["stages"]) == {"first", *design_study.CONDITIONS}
        for stage in seed["stages"].values():
            assert stage["band_width_m"] > 0 and np.all(np.isfinite(stage["std"]))
    assert isinstance(res["summary"]["design_never_widens_band"], bool)
    assert programs.builds == 2 and len(programs) == 2  # built once, used by every stage
    md = (out / "results.md").read_text()
    assert design_study.main(["--resummarise", "--out", str(out)]) == 0
    assert (out / "results.md").read_text() == md
