"""The force-noise term with one Jacobian per lobe (treeinfer.model.force_noise_local) against
independent references: near each reference the blended density is the exact
errors-in-variables MVN (scipy.stats.multivariate_normal with ``C`` from the Jacobian AT that
point), where the term linearised at the other reference is off by nats; the stacked basis pads,
splits and records as single ones do; the start pipeline's lobe search keeps distinct lobes
only."""

from __future__ import annotations

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from treeinfer.data.trajectories import Trajectory, stack_trajectories
from treeinfer.errors import ConfigError
from treeinfer.examples import example_path
from treeinfer.inference import start_pipeline as sp
from treeinfer.model import force_noise as fn
from treeinfer.model import force_noise_local as fl
from treeinfer.model.force_noise_model import ForceNoiseModel
from treeinfer.model.likelihood import gains_from_theta, likelihood_terms, theta_from_gains
from treeinfer.model.measurement import _padded_basis
from treeinfer.sim import make_simulator, simulate
from treeinfer.tree.description import load_tree

DT = 0.02
T = 50
THETA_A = theta_from_gains(np.array([40.0, 120.0]), np.array([0.5, 1.5]))
# another lobe: both stiffnesses a factor e^1.2 softer, the dampings e^0.3 higher
THETA_B = THETA_A + np.array([-1.2, -1.2, 0.3, 0.3])


@pytest.fixture(scope="module")
def case():
    sim = make_simulator(load_tree(example_path("two_branch")), obs_dt=DT)
    t = np.arange(T) * DT
    forces = np.stack([np.clip(t / 0.5, 0.0, 1.0) * p for p in (3.0, 5.0)])
    kp, kd = gains_from_theta(jnp.asarray(THETA_B[None], jnp.float32), sim.n_joints)
    tau = np.asarray(simulate(sim, kp, kd, jnp.asarray(forces, jnp.float32)).tau[0], float)
    rng = np.random.default_rng(3)
    sf = 0.05
    rec = tau + 0.002 * rng.standard_normal(tau.shape)
    rec_f = forces + sf * rng.standard_normal(forces.shape)
    obs = stack_trajectories([Trajectory(t, rec_f[b], rec[b], None, f"p{b}") for b in range(2)])
    return sim, obs, rec, sf


def _exact(sim, obs, rec, sf, theta, sx):
    """log MVN(rec | tau(theta), sigma_F^2 J(theta) J(theta)^T + sx^2 I), J AT theta (scipy)."""
    kp, kd = gains_from_theta(jnp.asarray(theta[None], jnp.float32), sim.n_joints)
    ro = jax.jit(lambda f: simulate(sim, kp, kd, f))(jnp.asarray(obs.force, jnp.float32))
    tau = np.asarray(ro.tau[0], float)
    cov = fn.force_noise_basis(sim, theta, obs.force, sf).covariance()
    return sum(
        stats.multivariate_normal(tau[b], cov[b] + sx**2 * np.eye(T)).logpdf(rec[b])
        for b in range(len(rec))
    )


def test_blend_is_exact_near_each_reference(case):
    sim, obs, rec, sf = case
    sx = 0.002
    both = likelihood_terms(
        sim, obs, "gaussian", noise_force=sf, force_noise_reference=np.stack([THETA_A, THETA_B])
    )
    only_a = likelihood_terms(sim, obs, "gaussian", noise_force=sf, force_noise_reference=THETA_A)
    assert np.shape(both.force_noise.theta_ref) == (2, 4)
    assert fl.is_stacked(both.force_noise.basis(sim, obs.force))
    # at lobe B (where the data were made) and near it: the blend is the exact density with J
    # at that very point, to float32 rounding at B, to the bias correction's first order and the
    # other reference's weight (e^-6) 0.05 log units away
    near_b = THETA_B + np.array([0.03, -0.02, 0.05, 0.0])
    for theta, tol in ((THETA_B, 0.01), (near_b, 0.1)):
        row = jnp.asarray(np.concatenate([theta, [np.log(sx)]])[None], jnp.float32)
        exact = _exact(sim, obs, rec, sf, theta, sx)
        assert float(jax.jit(both.log_likelihood)(row)[0]) == pytest.approx(exact, abs=tol)
        # the point of the blend: linearised in lobe A, lobe B's density is off (1 and 14 nats)
        single = float(jax.jit(only_a.log_likelihood)(row)[0])
        assert abs(single - exact) > 0.5
    # the weights: each reference holds near itself, smooth (sum 1) between
    w = np.asarray(fl.reference_weights(np.stack([THETA_A, THETA_B, 0.5 * (THETA_A + THETA_B)]),
                                        np.stack([THETA_A, THETA_B])))  # fmt: skip
    np.testing.assert_allclose(w.sum(1), 1.0, rtol=1e-6)
    assert w[0, 0] > 0.99 and w[1, 1] > 0.99 and w[2, 0] == pytest.approx(0.5, abs=1e-6)


def test_stacked_basis_pads_splits_and_records(case):
    sim, obs, _, sf = case
    model = ForceNoiseModel(sf, np.stack([THETA_A, THETA_B]), "test")
    basis = model.basis(sim, obs.force)
    parts = fl.split(basis)
    assert len(parts) == 2 and np.shape(basis.vectors) == (2, 2, T, T)
    single = fn.force_noise_basis(sim, THETA_B, obs.force, sf)
    np.testing.assert_allclose(parts[1].values, single.values, rtol=1e-12)
    mask = np.ones((3, T + 4), bool)
    mask[:, T:] = False
    padded = _padded_basis(basis, mask)
    for got, part in zip(fl.split(padded), parts):
        want = _padded_basis(part._replace(theta_ref=None), mask)
        np.testing.assert_array_equal(got.vectors, want.vectors)
        np.testing.assert_array_equal(got.values, want.values)
    # the primary reference's diag C for the bands
    np.testing.assert_allclose(
        fn.point_variance(basis),
        fn.point_variance(fn.force_noise_basis(sim, THETA_A, obs.force, sf)),
        rtol=1e-12,
    )
    rec = model.settings()["noise_force_reference"]
    np.testing.assert_allclose(fl.check_references(rec, 4), np.stack([THETA_A, THETA_B]))
    np.testing.assert_allclose(fl.check_references([list(THETA_A)], 4), THETA_A)  # one row
    for bad in ([1.0, 2.0], [[np.nan] * 4], np.zeros((1, 2, 4))):
        with pytest.raises(ConfigError, match="force_noise_reference"):
            fl.check_references(bad, 4)


def test_lobe_search_keeps_distinct_lobes_within_the_gap(monkeypatch):
    """Gains [kp_x, kp_y, kd_x, kd_y] and a noise column. Candidates: a final near the reference
    (skipped), two far in a stiffness within the gap (fitted at themselves, kept), one far in a
    damping only (one lobe: skipped), one beyond the gap (skipped), an earlier round's MAP that
    the fit takes back into a known lobe (dropped), a far one along a weakly identified
    stiffness (the same lobe)."""
    ref = np.zeros(4)
    finals = np.array(
        [
            [0.1, 0.0, 0.0, 0.0, -6.0],
            [2.0, 0.0, 0.0, 0.0, -6.0],
            [0.0, 0.0, 3.0, 0.0, -6.0],
            [0.0, 3.0, 0.0, 0.0, -6.0],
            [-3.0, 0.0, 0.0, 0.0, -6.0],
        ]
    )
    values = np.array([0.0, 2.0, 2.5, 3.0, sp.LOBE_GAP + 1.0])
    calls = []

    def fit_at(at, starts):  # each lobe's own MAP: lobes at kp_x = 2.3 and kp_y = 3; 0 else
        calls.append(np.array(at))
        x = np.array(starts[0], float)
        if x[0] > 1.0:
            x[:4], v = [2.3, 0.0, 0.0, 0.0], 1.0
        elif x[1] > 1.0:
            x[:4], v = [0.0, 3.0, 0.0, 0.0], 2.0
        else:
            x[:4], v = [0.05, 0.0, 0.0, 0.0], 0.5
        return SimpleNamespace(theta=x, neg_log_posterior=v)

    def gains(th):
        return np.asarray(th)[:4]

    last = SimpleNamespace(finals=finals, values=values, cov=0.01 * np.eye(5))  # sd 0.1
    earlier = [np.array([0.8, 0.0, 0.0, 0.0, -6.0])]
    monkeypatch.setattr(sp, "MAX_REFERENCES", 4)
    refs, lobes = sp.lobe_references(fit_at, ref, last, earlier, gains)
    np.testing.assert_allclose(refs, [[0, 0, 0, 0], [2.3, 0, 0, 0], [0, 3, 0, 0]])
    assert len(lobes) == 2
    # the kp_x lobe moved 0.3 from its candidate: linearised again at its MAP
    assert any(np.allclose(c, [2.3, 0, 0, 0]) for c in calls)
    assert len(calls) == 5  # kp_x lobe twice, kp_y lobe, the earlier MAP twice (then dropped)
    monkeypatch.setattr(sp, "MAX_REFERENCES", 2)
    assert sp.lobe_references(fit_at, ref, last, earlier, gains)[0].shape == (2, 4)
    # a lobe 2 nats below the best under its own linearisation: kept only within LOBE_KEEP
    monkeypatch.setattr(sp, "MAX_REFERENCES", 4)
    monkeypatch.setattr(sp, "LOBE_KEEP", 1.5)
    refs4, _ = sp.lobe_references(fit_at, ref, last, earlier, gains)
    np.testing.assert_allclose(refs4, [[0, 0, 0, 0], [2.3, 0, 0, 0]])
    monkeypatch.setattr(sp, "LOBE_KEEP", 5.0)
    # kp_y weakly identified (sd 2): 3 log units along it are 1.5 sd, the same lobe
    wide = SimpleNamespace(finals=finals, values=values, cov=np.diag([0.01, 4, 0.01, 0.01, 0.01]))
    refs3, _ = sp.lobe_references(fit_at, ref, wide, [], gains)
    np.testing.assert_allclose(refs3, [[0, 0, 0, 0], [2.3, 0, 0, 0]])
    one = SimpleNamespace(finals=finals[:1], values=values[:1], cov=None)
    assert sp.lobe_references(fit_at, ref, one, [], gains)[0].shape == (1, 4)
