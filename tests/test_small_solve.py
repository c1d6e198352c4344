"""treeinfer.sim.small_solve (LAPACK-free small solves) and the static model's use of it (issue 13).

The stem study's 0.36 m fold hung for ever: jaxlib 0.10's batched LAPACK LU splits its batch over
XLA's CPU thread pool and blocks the pool thread it runs on, so two LUs at once on a 2-core
machine deadlock. The static model's programs must hold no LAPACK call.
"""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from treeinfer.examples import example_path
from treeinfer.inference.static import static_rollout
from treeinfer.sim import make_simulator
from treeinfer.sim.small_solve import lu_factor, solve
from treeinfer.tree.description import load_tree


def _lapack_calls(compiled_text: str) -> list[str]:
    """The LAPACK custom-call targets of a compiled program's HLO text."""
    targets = re.findall(r'custom_call_target="([^"]+)"', compiled_text)
    return sorted({t for t in targets if "lapack" in t})


@pytest.mark.parametrize("n", [1, 2, 3, 8])
def test_solve_matches_numpy_with_pivoting(n):
    """x, and the gradients d(c.x)/db = a^-T c and d(c.x)/da = -(a^-T c) x^T, against numpy's
    LAPACK solves in float64; a[0, 0] = 0 forces a row exchange."""
    rng = np.random.default_rng(n)
    a = rng.normal(size=(n, n)) + (0.0 if n > 1 else 1.0)
    if n > 1:
        a[0, 0] = 0.0
    b, c = rng.normal(size=n), rng.normal(size=n)
    with jax.enable_x64(True):
        x = np.asarray(solve(jnp.asarray(a), jnp.asarray(b)))
        ga, gb = jax.grad(lambda aa, bb: solve(aa, bb) @ jnp.asarray(c), argnums=(0, 1))(
            jnp.asarray(a), jnp.asarray(b)
        )
        xt = np.asarray(jax.jvp(lambda bb: solve(jnp.asarray(a), bb), (b,), (c,))[1])
    want = np.linalg.solve(a, b)
    lam = np.linalg.solve(a.T, c)
    np.testing.assert_allclose(x, want, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.asarray(gb), lam, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.asarray(ga), -np.outer(lam, want), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(xt, np.linalg.solve(a, c), rtol=1e-10, atol=1e-12)


def test_lu_factor_reconstructs_and_batches():
    rng = np.random.default_rng(7)
    a = rng.normal(size=(50, 6, 6))
    b = rng.normal(size=(50, 6))
    with jax.enable_x64(True):
        lu, perm = jax.vmap(lu_factor)(jnp.asarray(a))
        x = jax.jit(jax.vmap(solve))(jnp.asarray(a), jnp.asarray(b))
    lu, perm = np.asarray(lu), np.asarray(perm)
    low = np.tril(lu, -1) + np.eye(6)
    up = np.triu(lu)
    np.testing.assert_allclose(low @ up, np.take_along_axis(a, perm[:, :, None], 1), atol=1e-12)
    want = np.linalg.solve(a, b[..., None])[..., 0]
    np.testing.assert_allclose(np.asarray(x), want, rtol=1e-8, atol=1e-10)
    with pytest.raises(ValueError, match="square"):
        lu_factor(jnp.ones((2, 3)))


def test_static_programs_hold_no_lapack_call():
    """The static model's gradient program (two grasp groups, value and tangent: batched solves
    that XLA may run at once) compiles without any LAPACK custom call. Before the fix both held
    ``lapack_sgetrf_ffi`` (the LU that deadlocked the CPU pool)."""
    tree = load_tree(example_path("three_branch"))
    sim = make_simulator(tree, obs_dt=0.5, backend="fused")
    branches = ("branch2", "branch1")
    forces = jnp.asarray([[0.0, 1.0, 2.0], [0.0, 0.5, 1.0]])
    kp0 = jnp.full((2, len(sim.dof_ids)), 40.0)

    def value(kp):
        r = static_rollout(sim, kp, forces, grasp_branch=branches, tree=tree)
        return jnp.sum(r.tau**2)

    grad = jax.jit(jax.grad(value)).lower(kp0).compile()  # holds the value's program too
    calls = _lapack_calls(grad.as_text())
    assert calls == [], f"LAPACK custom calls in the static gradient: {calls}"
    g = grad(kp0)
    assert np.all(np.isfinite(np.asarray(g))) and float(jnp.max(jnp.abs(g))) > 0
