"""Dense linear solves of small systems without LAPACK: safe inside batched jitted code on CPU.

Why not ``jnp.linalg.solve``: on the CPU, jaxlib 0.10 runs a batched LU (``lapack_?getrf_ffi``)
by splitting its batch over XLA's intra-op thread pool (``jax::ParallelBatchMap``) and blocking
the calling pool thread until the pieces are done. When the thunk executor runs as many
independent batched LAPACK calls at once as the pool has threads (two on a 2-core machine: e.g.
the static model's two grasp groups, or a value and its tangent), every pool thread waits for
work queued behind it and the process sleeps on a futex forever (issue 13: the stem study's
0.36 m fold; gdb showed both ``tf_XLAEigen`` threads in ``BlockingCounter::Wait`` under
``LuDecomposition::Kernel``). jaxlib 0.11 drops that parallel path; until the pinned version has
it, the solvers of the equilibria use this one: Gaussian elimination with partial pivoting
written in ``jax.numpy`` (``lax.fori_loop`` over columns, so the program size does not grow
with the system), which XLA compiles to ordinary fused loops with no custom call. For the
systems solved here (``n`` = the tree's dofs, 2-30) it costs about what LAPACK does.

Derivatives follow ``jnp.linalg.solve``: the factorisation is wrapped in
``lax.custom_linear_solve`` (forward and reverse mode, any order, with respect to both ``a`` and
``b``; the transpose solve reuses the factors).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["lu_factor", "lu_solve", "solve"]


def lu_factor(a: jax.Array) -> tuple[jax.Array, jax.Array]:
    """LU factorisation with partial pivoting of one square matrix ``a`` [n, n].

    Returns:
      ``(lu, perm)``: ``lu`` [n, n] holds U on and above the diagonal and the unit lower factor
      L below it; ``perm`` [n] int32 the row order, ``a[perm] = L U`` (LAPACK's ``getrf`` up to
      the encoding of the pivots). A zero pivot (a singular ``a``) gives inf/NaN entries, as
      LAPACK's solve does.
    """
    a = jnp.asarray(a)
    n = a.shape[-1]
    if a.ndim != 2 or a.shape[0] != n:
        raise ValueError(f"lu_factor: a must be square [n, n], got shape {a.shape}")
    idx = jnp.arange(n)

    def column(k, carry):
        a, perm = carry
        # pivot: the largest |entry| of column k on or below the diagonal
        p = jnp.argmax(jnp.where(idx >= k, jnp.abs(a[:, k]), -1.0))
        order = jnp.where(idx == k, p, jnp.where(idx == p, k, idx))
        a, perm = a[order], perm[order]
        below = idx > k
        lower = jnp.where(below, a[:, k] / a[k, k], 0.0)  # multipliers [n]
        right = jnp.where(idx > k, a[k], 0.0)  # the pivot row right of the diagonal [n]
        a = a - lower[:, None] * right[None, :]
        a = jnp.where(below[:, None] & (idx[None, :] == k), lower[:, None], a)
        return a, perm

    return jax.lax.fori_loop(0, n, column, (a, idx.astype(jnp.int32)))


def lu_solve(lu: jax.Array, perm: jax.Array, b: jax.Array, transpose: bool = False) -> jax.Array:
    """Solve ``a x = b`` (or ``a^T x = b`` with ``transpose``) from :func:`lu_factor`'s factors.

    Args:
      lu, perm: from :func:`lu_factor` of ``a`` [n, n].
      b: [n] right-hand side.

    Returns:
      x [n].
    """
    n = lu.shape[-1]
    idx = jnp.arange(n)

    def forward(unit: bool, mat):  # lower-triangular solve, rows 0..n-1
        def row(i, y):
            s = jnp.sum(jnp.where(idx < i, mat[i], 0.0) * y)
            v = y[i] - s if unit else (y[i] - s) / mat[i, i]
            return y.at[i].set(v)

        return row

    def backward(unit: bool, mat):  # upper-triangular solve, rows n-1..0
        def row(k, y):
            i = n - 1 - k
            s = jnp.sum(jnp.where(idx > i, mat[i], 0.0) * y)
            v = y[i] - s if unit else (y[i] - s) / mat[i, i]
            return y.at[i].set(v)

        return row

    if not transpose:  # P a = L U: L y = P b, U x = y
        y = jax.lax.fori_loop(0, n, forward(True, lu), b[perm])
        return jax.lax.fori_loop(0, n, backward(False, lu), y)
    # a^T = U^T L^T P: U^T y = b, L^T z = y, x = P^T z
    lu_t = lu.T
    y = jax.lax.fori_loop(0, n, forward(False, lu_t), b)
    z = jax.lax.fori_loop(0, n, backward(True, lu_t), y)
    return jnp.zeros_like(z).at[perm].set(z)


def solve(a: jax.Array, b: jax.Array) -> jax.Array:
    """``x = a^-1 b`` for one small square system, without a LAPACK call (see the module).

    Args:
      a: [n, n]; b: [n]. Batch with ``jax.vmap``.

    Returns:
      x [n], differentiable in ``a`` and ``b`` (forward and reverse, any order).
    """
    a = jnp.asarray(a)
    b = jnp.asarray(b)
    if b.ndim != 1 or a.shape != (b.shape[0], b.shape[0]):
        raise ValueError(f"solve: need a [n, n] and b [n], got {a.shape} and {b.shape}")
    dtype = jnp.result_type(a, b)
    a, b = a.astype(dtype), b.astype(dtype)
    lu, perm = lu_factor(jax.lax.stop_gradient(a))
    return jax.lax.custom_linear_solve(
        lambda x: a @ x,
        b,
        solve=lambda _, x: lu_solve(lu, perm, x),
        transpose_solve=lambda _, x: lu_solve(lu, perm, x, transpose=True),
    )
