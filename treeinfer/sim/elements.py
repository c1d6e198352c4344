"""Element arithmetic with constant folding, for :mod:`treeinfer.sim.fused`'s step.

An *element* is a Python float (a compile-time constant: products with the model's many exact
zeros and ones vanish at trace time) or a JAX scalar; the vector and matrix helpers work on
tuples of elements, so XLA sees scalar multiply-adds it can fuse into one kernel.
"""

from __future__ import annotations

import numpy as np


# ---- element arithmetic with constant folding ---------------------------------------------------
def _const(x) -> float:
    x = float(x)
    return 0.0 if abs(x) < 1e-15 else x


def _is(x, value: float) -> bool:
    return isinstance(x, float) and x == value


def add(a, b):
    if _is(a, 0.0):
        return b
    if _is(b, 0.0):
        return a
    return a + b


def sub(a, b):
    if _is(b, 0.0):
        return a
    if _is(a, 0.0):
        return -b
    return a - b


def mul(a, b):
    if _is(a, 0.0) or _is(b, 0.0):
        return 0.0
    if _is(a, 1.0):
        return b
    if _is(b, 1.0):
        return a
    return a * b


def total(*terms):
    out = 0.0
    for t in terms:
        out = add(out, t)
    return out


def vadd(u, v):
    return tuple(add(a, b) for a, b in zip(u, v))


def vsub(u, v):
    return tuple(sub(a, b) for a, b in zip(u, v))


def vscale(s, v):
    return tuple(mul(s, a) for a in v)


def dot(u, v):
    return total(*(mul(a, b) for a, b in zip(u, v)))


def cross(u, v):
    return (
        sub(mul(u[1], v[2]), mul(u[2], v[1])),
        sub(mul(u[2], v[0]), mul(u[0], v[2])),
        sub(mul(u[0], v[1]), mul(u[1], v[0])),
    )


def matvec(m, v):
    return tuple(dot(row, v) for row in m)


def matTvec(m, v):
    return tuple(total(*(mul(m[k][i], v[k]) for k in range(3))) for i in range(3))


def matmul(a, b):
    return tuple(
        tuple(total(*(mul(a[i][k], b[k][j]) for k in range(3))) for j in range(3)) for i in range(3)
    )


_ZERO3 = (0.0, 0.0, 0.0)
_EYE3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def _cvec(v):
    return tuple(_const(x) for x in np.asarray(v, float).reshape(3))


def _cmat(m):
    return tuple(tuple(_const(x) for x in row) for row in np.asarray(m, float).reshape(3, 3))
