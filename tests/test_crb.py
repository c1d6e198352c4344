"""The Cramér–Rao bound behind issue 11's "posterior std within 2x of the CRB" figures
(``experiments/coverage.py::crb_log_std``), against an independent computation.

On noise-free data at the true gains the Gaussian log-likelihood's residuals vanish, so its
Hessian there IS minus the Fisher information ``J^T J / sigma^2`` (the second-derivative term
is multiplied by the residual). The reference is that Hessian: central differences of the
exact reverse-mode gradient of treeinfer's own Gaussian log-likelihood (``make_problem(...,
gradient="autodiff")``), where ``crb_log_std`` uses a central-difference Jacobian of the
simulated displacement. Different routes, same number."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments.coverage import SIGMA_X, crb_log_std
from treeinfer.data.trajectories import Trajectory, stack_trajectories
from treeinfer.examples import example_path
from treeinfer.inference.problem import make_problem
from treeinfer.model.likelihood import likelihood_terms
from treeinfer.sim import make_simulator, simulate
from treeinfer.tree.description import load_tree

KP, KD = np.array([37.7, 98.7]), np.array([0.365, 1.047])  # child, parent (the demo's truth)


def two_branch_pulls():
    """Two ramp-and-hold pulls of the two_branch example (60 samples at 20 ms, 8 substeps) at
    the true gains: ``(tree, sim, t [T], forces [2, T], rollout)`` (also used by
    ``test_noise_velocity.py``)."""
    tree = load_tree(example_path("two_branch"))
    dt, n = 0.02, 60
    sim = make_simulator(tree, obs_dt=dt, substeps=8)
    t = np.arange(n) * dt
    forces = np.stack([np.clip(t / 0.5, 0.0, 1.0) * p for p in (4.0, 7.0)])
    roll = simulate(sim, jnp.asarray(KP[None]), jnp.asarray(KD[None]), jnp.asarray(forces))
    return tree, sim, t, forces, roll


@pytest.fixture(scope="module")
def clean():
    """Noise-free pulls at the true gains: ``(tree, sim, train)``."""
    tree, sim, t, forces, roll = two_branch_pulls()
    train = [
        Trajectory(t, forces[b], np.asarray(roll.tau[0, b], float), None, f"p{b}") for b in range(2)
    ]
    return tree, sim, train


def _inverse_hessian_std(log_likelihood) -> np.ndarray:
    """sqrt diag of (-Hessian)^-1 at the truth: central differences (step 2e-3 in log units) of
    the exact reverse-mode gradient of ``log_likelihood`` (batched ``[N, D] -> [N]``)."""
    grad = jax.jit(jax.grad(lambda th: log_likelihood(th[None])[0]))
    theta = jnp.asarray(np.log(np.concatenate([KP, KD])), jnp.float32)
    h = 2e-3
    eye = np.eye(4, dtype=np.float32)
    hess = np.stack(
        [(np.asarray(grad(theta + h * e)) - np.asarray(grad(theta - h * e))) / (2 * h) for e in eye]
    )
    hess = 0.5 * (hess + hess.T)
    return np.sqrt(np.diag(np.linalg.inv(-hess)))


def test_crb_equals_the_inverse_hessian_of_the_gaussian_likelihood(clean):
    tree, sim, train = clean
    crb = crb_log_std(sim, KP, KD, train)
    prob = make_problem(
        tree,
        train,
        sim=sim,
        nn_prior=False,
        likelihood="gaussian",
        noise_displacement=SIGMA_X,
        gradient="autodiff",
    )
    ref = _inverse_hessian_std(prob.log_likelihood)
    # measured: agree to 0.2% (float32 simulator; the damping of the child is the loosest)
    np.testing.assert_allclose(crb, ref, rtol=0.02)
    assert crb[0] < crb[2]  # the child's stiffness is far better identified than its damping


def test_crb_with_force_noise_equals_the_errors_in_variables_hessian(clean):
    """With force noise the bound is ``sum_b J_b^T (C_b + sigma^2 I)^-1 J_b``; the reference is
    the Hessian of treeinfer's errors-in-variables likelihood with its force Jacobian taken at
    the truth (``force_noise_reference``), again at zero residual."""
    _, sim, train = clean
    sigma_f = 0.14  # N, 2% of the larger pull's 7 N
    crb = crb_log_std(sim, KP, KD, train, sigma_force=sigma_f)
    terms = likelihood_terms(
        sim,
        stack_trajectories(train),
        "gaussian",
        sigma_x=SIGMA_X,
        gradient="autodiff",
        noise_force=sigma_f,
        force_noise_reference=np.log(np.concatenate([KP, KD])),
    )
    ref = _inverse_hessian_std(terms.log_likelihood)
    np.testing.assert_allclose(crb, ref, rtol=0.02)
    # the force noise destroys information: every bound is wider than the white-noise one
    assert np.all(crb > crb_log_std(sim, KP, KD, train))
