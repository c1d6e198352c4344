"""Plausibility checks before inference and fit checks after it (issue 14, item 3).

Each corrupted case of the issue's campaign is built small here from one clean simulated data
set (MJX/fused simulator, noise added); the clean set itself must give no finding at all."""

from __future__ import annotations

import numpy as np
import pytest

from treeinfer.data.forces import ramp_hold
from treeinfer.data.trajectories import Trajectory, velocity_from_displacement, write_trajectory
from treeinfer.evaluation.checks import (
    compliance_range,
    data_checks,
    errors_of,
    fit_checks,
    lever_arm_compliance,
    noise_from_kT,
    static_compliance,
)
from treeinfer.examples import example_path
from treeinfer.model.likelihood import suggest_kT
from treeinfer.tree.description import load_tree

DT = 0.02
TRUE_KP = (60.0, 120.0)
TRUE_KD = (1.0, 2.0)
SIGMA = 1e-3


@pytest.fixture(scope="module")
def tree():
    return load_tree(example_path("two_branch"))


@pytest.fixture(scope="module")
def clean(tree):
    """Three simulated pulls (2 s at 50 Hz) with 1 mm displacement noise and a velocity column
    differentiated from the noisy displacement, as `treeinfer simulate` writes them."""
    make_simulator, simulate = _sim()

    sim = make_simulator(tree, obs_dt=DT)
    forces = np.stack([ramp_hold(p, 0.4, 0.6, 0.4, 2.0, DT) for p in (3.0, 4.0, 2.0)])
    roll = simulate(sim, np.array([TRUE_KP]), np.array([TRUE_KD]), forces)
    assert np.asarray(roll.stable).all()
    tau = np.asarray(roll.tau, float)[0]
    rng = np.random.default_rng(0)
    out = []
    for b in range(3):
        t = np.arange(forces.shape[1]) * DT
        x = tau[b] + SIGMA * rng.standard_normal(t.shape)
        x[0] = 0.0
        out.append(
            Trajectory(
                t, forces[b].astype(float), x, velocity_from_displacement(x, DT), f"pull{b}.csv"
            )
        )
    return out


def _sim():
    """make_simulator, simulate from treeinfer.sim (or treeinfer.simulator before the split)."""
    try:
        from treeinfer.sim import make_simulator, simulate
    except ImportError:
        from treeinfer.simulator import make_simulator, simulate
    return make_simulator, simulate


def _checks(tree, trajs, **kw):
    return data_checks(tree, trajs, **kw)


def _only(findings, check, severity=None):
    hits = [
        f for f in findings if f.check == check and (severity is None or f.severity == severity)
    ]
    assert hits, f"no '{check}' finding in {findings}"
    return hits


# ---- the compliance estimate against MuJoCo ------------------------------------------------
def test_static_compliance_matches_a_settled_mujoco_pull(tree):
    """Independent reference: the MJX/fused rollout's displacement after a slow 0.5 N ramp has
    settled, divided by the force, at a soft, a stiff and a mixed corner of the box."""
    from treeinfer.data.forces import ramp

    make_simulator, simulate = _sim()

    sim = make_simulator(tree, obs_dt=0.01)
    f = ramp(0.5, 1.0, 4.0, 0.01)
    for kp in [(50.0, 100.0), (500.0, 500.0), (5.0, 500.0)]:
        roll = simulate(sim, np.array([kp]), np.array([[3.0, 3.0]]), f[None])
        measured = float(np.asarray(roll.tau)[0, 0, -1]) / 0.5
        c = static_compliance(tree, dict(zip(tree.inferred, kp)))
        assert c == pytest.approx(measured, rel=0.03)
    # stiff joints: gravity's stiffness is negligible, the lever-arm formula agrees too
    kp = dict(zip(tree.inferred, (500.0, 500.0)))
    assert lever_arm_compliance(tree, kp) == pytest.approx(static_compliance(tree, kp), rel=0.03)
    c_stiff, c_soft = compliance_range(tree)
    assert c_stiff < static_compliance(tree, dict(zip(tree.inferred, TRUE_KP))) < c_soft


def test_compliance_range_covers_the_box_where_compliance_is_not_monotone():
    """A soft joint lets the branch hang along gravity, where a downward pull has little lever
    arm: on the three-branch example the compliance peaks inside the box (0.11 m/N at Kp ~ 23,
    against 0.016 at the lower bound 5), and a slow pull simulated from the example's own model
    at in-box gains must not read as a unit mistake."""
    from treeinfer.data.forces import ramp

    tree3 = load_tree(example_path("three_branch"))
    least, most = compliance_range(tree3)
    ends = [static_compliance(tree3, {n: tree3.bounds[n].kp[i] for n in tree3.inferred})
            for i in (0, 1)]  # fmt: skip
    inside = static_compliance(tree3, {n: 23.0 for n in tree3.inferred})
    assert inside > 3 * max(ends)  # the ends alone missed it
    assert least <= min(ends) and most >= inside
    # a quasi-static pull of the example at Kp = 23 (independent: the simulator, not MuJoCo's
    # static Jacobians) gives no scale finding
    make_simulator, simulate = _sim()
    sim = make_simulator(tree3, obs_dt=DT)
    f = ramp(0.5, 1.0, 4.0, DT)
    roll = simulate(sim, np.full((1, 3), 23.0), np.full((1, 3), 3.0), f[None])
    x = np.asarray(roll.tau, float)[0, 0]
    assert x[-1] / 0.5 == pytest.approx(inside, rel=0.05)
    pull = Trajectory(np.arange(f.size) * DT, f, x, None, "slow.csv")
    assert not [h for h in data_checks(tree3, [pull]) if h.check == "scale"]


# ---- the clean set and each corruption -------------------------------------------------------
def test_clean_data_give_no_finding(tree, clean):
    assert _checks(tree, clean) == []


def _map(trajs, fn, which=None):
    return [fn(t) if which is None or i in which else t for i, t in enumerate(trajs)]


def test_displacement_in_cm_and_mm(tree, clean):
    cm = _checks(
        tree, _map(clean, lambda t: t._replace(displacement=100 * t.displacement, velocity=None))
    )
    assert len(_only(cm, "scale")) == 3 and "displacement is in cm" in _only(cm, "scale")[0].message
    mm = _checks(
        tree, _map(clean, lambda t: t._replace(displacement=1000 * t.displacement, velocity=None))
    )
    assert errors_of(mm), mm


def test_force_in_kN(tree, clean):
    f = _checks(tree, _map(clean, lambda t: t._replace(force=t.force / 1000.0)))
    hits = _only(f, "scale", "error")
    assert hits[0].file == "pull0.csv" and "force in kN" in hits[0].message


def test_swapped_columns(tree, clean):
    f = _checks(
        tree,
        _map(
            clean, lambda t: t._replace(force=t.displacement, displacement=t.force, velocity=None)
        ),
    )
    assert "columns were swapped" in _only(f, "scale", "error")[0].message
    assert _only(f, "reach", "error")


def test_offset_displacement(tree, clean):
    f = _checks(
        tree, _map(clean, lambda t: t._replace(displacement=t.displacement + 1.9, velocity=None))
    )
    hits = _only(f, "rest", "error")
    assert "starts at 1.9 m" in hits[0].message


def test_mixed_units_between_files(tree, clean):
    f = _checks(
        tree,
        _map(
            clean, lambda t: t._replace(displacement=100 * t.displacement, velocity=None), which={1}
        ),
    )
    hits = _only(f, "mixed-units", "error")
    assert [h.file for h in hits] == ["pull1.csv"]


def test_sign_mismatch(tree, clean):
    f = _checks(tree, _map(clean, lambda t: t._replace(force=-t.force)))
    assert len(_only(f, "sign", "error")) == 3


@pytest.mark.parametrize(
    "make, words",
    [
        (lambda t, rng: -t.velocity, "opposite sign"),
        (lambda t, rng: np.zeros_like(t.velocity), "all zero"),
        (
            lambda t, rng: rng.standard_normal(t.velocity.shape) * np.std(t.velocity),
            "does not follow",
        ),
        (lambda t, rng: t.velocity * 100.0, "100x the slope"),
    ],
)
def test_bad_velocity_column(tree, clean, make, words):
    rng = np.random.default_rng(1)
    f = _checks(tree, _map(clean, lambda t: t._replace(velocity=make(t, rng)), which={2}))
    hits = _only(f, "velocity", "error")
    assert hits[0].file == "pull2.csv" and words in hits[0].message


def test_time_in_minutes(tree, clean):
    """Every file of the set faster than the energy bound allows: the clock, an error (issue 28:
    a silent wrong-unit case before, a warning only); one file alone only where it breaks the
    bound by TIME_UNIT_ERROR or more (a glitch in one recording does not stop the run)."""
    from treeinfer.data.checks import TIME_UNIT_ERROR

    minutes = _map(clean, lambda t: t._replace(time=t.time / 60.0, velocity=None))
    f = _checks(tree, minutes)
    hits = _only(f, "time-unit", "error")
    assert len(hits) == 3 and "every file of the set" in hits[0].message
    assert "minutes instead of seconds" in hits[0].message
    one = _checks(tree, [minutes[0], *clean[1:]])
    (hit,) = _only(one, "time-unit")
    ratio = float(hit.message.split("x faster")[0].rsplit(" ", 1)[1])
    assert hit.severity == ("error" if ratio >= TIME_UNIT_ERROR else "warning")
    assert not [x for x in _checks(tree, clean) if x.check == "time-unit"]
    # with the velocity column (in m/s) the mismatch is an error naming the factor
    f = _checks(tree, _map(clean, lambda t: t._replace(time=t.time / 60.0)))
    msg = _only(f, "velocity", "error")[0].message
    assert "x the slope" in msg and "0.016" in msg


def test_duplicates(tree, clean, tmp_path):
    trajs = [clean[0], clean[1], clean[0]._replace(source="copy.csv")]
    hits = _only(_checks(tree, trajs), "duplicate", "error")
    assert hits[0].file == "copy.csv" and "pull0.csv" in hits[0].message
    paths = []
    for name, t in (("a.csv", clean[0]), ("b.csv", clean[1])):
        paths.append(write_trajectory(tmp_path / name, t))
    (tmp_path / "c.csv").write_bytes(paths[0].read_bytes())
    paths.append(tmp_path / "c.csv")
    hits = _only(_checks(tree, [clean[0], clean[1], clean[0]], paths=paths), "duplicate")
    assert "byte-identical" in hits[0].message and hits[0].file.endswith("c.csv")


def test_all_zero(tree, clean):
    z = clean[0]._replace(
        force=0 * clean[0].force, displacement=0 * clean[0].displacement, velocity=None
    )
    assert _only(_checks(tree, [z]), "all-zero", "error")
    z = clean[0]._replace(displacement=0 * clean[0].displacement, velocity=None)
    assert "displacement is zero" in _only(_checks(tree, [z]), "all-zero")[0].message


def test_stiffness_outside_the_prior_box(tree, clean):
    """Quasi-static data of a tree at Kp = 20000 (40x the box's upper bound)."""
    c = static_compliance(tree, dict(zip(tree.inferred, (20000.0, 20000.0))))
    trajs = _map(
        clean, lambda t: t._replace(displacement=c * (t.force - t.force[0]), velocity=None)
    )
    hits = _only(_checks(tree, trajs), "scale", "warning")
    assert "stiffer than the prior box allows" in hits[0].message


def test_mm_tree_lengths_warn_or_fail(tree):
    import yaml

    from treeinfer.errors import TreeFileError
    from treeinfer.tree.description import tree_from_dict

    d = yaml.safe_load(example_path("two_branch").read_text())
    for b in d["branches"]:
        b["length"] *= 1000.0
        b["radius"] *= 1000.0
    with pytest.raises(TreeFileError, match="looks like millimetres"):
        tree_from_dict(d, "mm.yaml")


# ---- fit checks ------------------------------------------------------------------------------
def _box(tree):
    lo, hi = tree.bounds_array()
    return np.log(lo), np.log(hi)


def test_fit_ok_for_a_concentrated_posterior_in_the_box(tree):
    lo, hi = _box(tree)
    rng = np.random.default_rng(0)
    theta = np.log(np.array([*TRUE_KP, *TRUE_KD])) + 0.05 * rng.standard_normal((64, 4))
    v = fit_checks(
        residuals=SIGMA * rng.standard_normal((3, 100)),
        noise_sigma=SIGMA,
        fraction_outside=0.04,
        theta=theta,
        lower=lo,
        upper=hi,
        labels=tree.parameter_labels(),
    )
    assert v.status == "ok" and v.reasons == []


def test_fit_cm_data_is_poor(tree):
    """The issue's cm run: 93.3% of points outside the band."""
    v = fit_checks(fraction_outside=0.933)
    assert v.status == "poor_fit" and "93.3% of training points" in v.reasons[0]
    sigma = noise_from_kT(suggest_kT(2e-3, 50, DT), 50, DT)  # 2 mm
    v = fit_checks(residuals=np.full((2, 50), 0.05), noise_sigma=sigma)
    assert v.status == "poor_fit" and "x the noise scale" in v.reasons[0]


def test_noise_from_kT_inverts_suggest_kT():
    assert noise_from_kT(suggest_kT(2e-3, 300, 0.01), 300, 0.01) == pytest.approx(2e-3)


def test_fit_posterior_at_the_prior_edge(tree):
    """Kp = 20000 data with the default box: particles pile up beyond the upper Kp bound."""
    lo, hi = _box(tree)
    rng = np.random.default_rng(0)
    theta = np.column_stack(
        [
            hi[0] + 0.3 + 0.1 * rng.standard_normal(64),
            hi[1] - 0.01 * rng.random(64),
            np.log(1.0) + 0.1 * rng.standard_normal(64),
            np.log(2.0) + 0.1 * rng.standard_normal(64),
        ]
    )
    v = fit_checks(theta=theta, lower=lo, upper=hi, labels=tree.parameter_labels())
    assert v.status == "poor_fit"
    assert any("Kp[child]" in r and "upper bound" in r for r in v.reasons)
    assert v.measures["at_prior_edge"] == {"Kp[child]": "upper", "Kp[parent]": "upper"}


def test_fit_prior_back_when_data_have_no_effect(tree):
    """kT = 1e9: the posterior is the prior (uniform over the log box)."""
    lo, hi = _box(tree)
    theta = lo + (hi - lo) * np.random.default_rng(0).random((256, 4))
    v = fit_checks(theta=theta, lower=lo, upper=hi, labels=tree.parameter_labels())
    assert v.status == "poor_fit" and "the data had no effect" in v.reasons[0]
    # only one parameter uninformed: a warning
    theta[:, :3] = np.log(np.array([*TRUE_KP, TRUE_KD[0]])) + 0.05 * np.random.default_rng(
        1
    ).standard_normal((256, 3))
    v = fit_checks(theta=theta, lower=lo, upper=hi, labels=tree.parameter_labels())
    assert v.status == "warning" and "barely narrowed Kd[parent]" in v.reasons[0]


def test_fit_verdict_from_run_and_preflight(tree, clean):
    from types import SimpleNamespace

    from treeinfer.data.trajectories import stack_trajectories
    from treeinfer.evaluation.checks import fit_verdict_from_run, preflight

    obs = stack_trajectories(clean)
    lo, hi = _box(tree)
    problem = SimpleNamespace(obs=obs, lower=lo, upper=hi, labels=tuple(tree.parameter_labels()))
    rng = np.random.default_rng(0)
    theta = np.log(np.array([*TRUE_KP, *TRUE_KD])) + 0.05 * rng.standard_normal((32, 4))
    pred = SimpleNamespace(
        mean=obs.displacement + SIGMA * rng.standard_normal(obs.displacement.shape)
    )
    fit = {"stable": np.ones(32, bool), "prediction": pred, "metrics": {"fraction_outside": 0.03}}
    v = fit_verdict_from_run(problem, SimpleNamespace(theta=theta), fit, noise_sigma=SIGMA)
    assert v.status == "ok", v
    pred.mean = 100 * obs.displacement  # a cm-type misfit: every point outside the band
    fit["metrics"] = {"fraction_outside": 1.0}
    v = fit_verdict_from_run(problem, SimpleNamespace(theta=theta), fit, noise_sigma=SIGMA)
    assert v.status == "poor_fit" and v.as_dict()["measures"]["residual_to_noise"] > 10
    fit["prediction"] = None
    v = fit_verdict_from_run(problem, SimpleNamespace(theta=theta), fit)
    assert v.status == "warning" and "too few stable particles" in v.reasons[0]
    errors, warnings = preflight(tree, [clean[0], clean[0]._replace(source="dup.csv")])
    assert [e.check for e in errors] == ["duplicate"] and warnings == []


def test_simulation_cost_check(tree):
    import dataclasses

    from treeinfer.evaluation.checks import simulation_cost_check
    from treeinfer.tree.description import Bounds

    assert simulation_cost_check(tree, 0.01) == []
    twig = dataclasses.replace(tree.branch("child"), length=0.1, radius=0.003)
    stiff = dataclasses.replace(
        tree,
        branches=(tree.branches[0], twig),
        bounds={n: Bounds(kp=(5.0, 1e8)) for n in tree.inferred},
    )
    f = simulation_cost_check(stiff, 0.01, "t.yaml")
    assert f and f[0].severity == "error" and "simulation steps per 0.01 s sample" in f[0].message


def test_misfit_called_noise_is_a_poor_fit(clean):
    """A generative fit that covers the recording only by calling a structured misfit noise
    (force in kgf: a compliance inside the prior box, so no data check sees it; issue 28's
    campaign ran it to exit 0) is poor_fit: fitted sigma_x >= 10x the recording's own noise,
    >= 10% of its range, residuals lag-1 >= 0.9. A fitted noise near the recording's own, or
    residuals that are white, never are."""
    from types import SimpleNamespace

    from treeinfer.data.trajectories import stack_trajectories
    from treeinfer.evaluation.checks import _misfit_called_noise
    from treeinfer.model.noise import estimate_displacement_noise

    obs = stack_trajectories(list(clean))
    own = estimate_displacement_noise(obs).sigma
    span = float(np.ptp(np.asarray(obs.displacement)[np.asarray(obs.mask, bool)]))
    problem = SimpleNamespace(labels=("Kp[a]", "sigma_x"), obs=obs)

    def post(sigma):
        return SimpleNamespace(theta=np.tile([0.0, np.log(sigma)], (8, 1)))

    big = max(20 * own, 0.3 * span)
    reason, m = _misfit_called_noise(problem, post(big), {"ppc": {"lag1": 0.99}})
    assert "kgf" in reason and m["fitted_sigma_m"] == pytest.approx(big)
    assert _misfit_called_noise(problem, post(big), {"ppc": {"lag1": 0.5}}) is None
    assert _misfit_called_noise(problem, post(1.2 * own), {"ppc": {"lag1": 0.99}}) is None
    no_noise = SimpleNamespace(labels=("Kp[a]",), obs=obs)
    assert _misfit_called_noise(no_noise, post(big), {"ppc": {"lag1": 0.99}}) is None


def test_noise_above_the_recordings_own_is_a_warning(clean):
    """A fitted sigma_x 1.3x the recording's own white noise or more (second differences) is
    flagged: on SBC of the default command the two fits in a wrong basin needed 2.1x and 3.4x,
    every right one 0.89-1.08x. Near the recording's own: nothing."""
    from types import SimpleNamespace

    from treeinfer.data.trajectories import stack_trajectories
    from treeinfer.evaluation.checks import NOISE_ABOVE_RECORDING, _noise_above_recording
    from treeinfer.model.noise import estimate_displacement_noise

    obs = stack_trajectories(list(clean))
    own = estimate_displacement_noise(obs).sigma
    problem = SimpleNamespace(labels=("Kp[a]", "sigma_x"), obs=obs)

    def post(sigma):
        return SimpleNamespace(theta=np.tile([0.0, np.log(sigma)], (8, 1)))

    reason, m = _noise_above_recording(problem, post(2.1 * own))
    assert "2.1x the recording's own" in reason and m["ratio"] == pytest.approx(2.1)
    assert _noise_above_recording(problem, post(1.05 * own)) is None
    assert _noise_above_recording(problem, post(0.9 * NOISE_ABOVE_RECORDING * own)) is None
    no_noise = SimpleNamespace(labels=("Kp[a]",), obs=obs)
    assert _noise_above_recording(no_noise, post(3 * own)) is None
