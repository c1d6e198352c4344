"""Statistics and bookkeeping shared by issue 27's measurement scripts
(``default_calibration.py``, ``sbc_default.py``): binomial intervals, the Cramer-Rao bound from a
Jacobian, and append-only JSON-lines records (so a study split over several GPU calls adds up).

Kept free of JAX and treeinfer imports: the smoke tests check these numbers against closed forms
in milliseconds.
"""

from __future__ import annotations

import gzip
import json
import math
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Exact (Clopper-Pearson) ``level`` interval of a binomial rate ``k / n`` (scipy's
    ``binomtest``; (0, 1) when ``n == 0``)."""
    if n == 0:
        return 0.0, 1.0
    from scipy.stats import binomtest

    ci = binomtest(int(k), int(n)).proportion_ci(level, method="exact")
    return float(ci.low), float(ci.high)


def rate_record(flags: Sequence[bool], nominal: float = 0.95) -> dict:
    """``{"k", "n", "rate", "clopper_pearson_95", "nominal_inside_ci"}`` of a list of hits
    (e.g. truth inside its 95% interval), against the ``nominal`` rate."""
    k, n = int(sum(bool(f) for f in flags)), len(flags)
    lo, hi = clopper_pearson(k, n)
    return {
        "k": k,
        "n": n,
        "rate": k / n if n else float("nan"),
        "clopper_pearson_95": [lo, hi],
        "nominal": nominal,
        "nominal_inside_ci": bool(lo <= nominal <= hi) if n else None,
    }


def crb_from_jacobian(jac, sigma: float, cov=None) -> np.ndarray:
    """Cramer-Rao standard deviation of each parameter of the Gaussian model
    ``y = f(theta) + e`` at the point where ``jac = df/dtheta`` [n, D] was taken.

    ``cov`` None: white noise of std ``sigma``, Fisher ``J^T J / sigma^2``. ``cov`` [n, n]:
    the noise covariance is ``cov + sigma^2 I`` (e.g. the errors-in-variables force term), Fisher
    ``J^T (cov + sigma^2 I)^-1 J``. Returns ``sqrt(diag(Fisher^-1))`` [D]; inf for a parameter
    the data do not inform (singular Fisher)."""
    j = np.asarray(jac, float)
    if j.ndim != 2:
        raise ValueError(f"crb_from_jacobian: jac must be [n, D], got shape {j.shape}")
    if not (math.isfinite(sigma) and sigma > 0):
        raise ValueError(f"crb_from_jacobian: sigma must be positive, got {sigma}")
    if cov is None:
        fisher = j.T @ j / sigma**2
    else:
        c = np.asarray(cov, float) + sigma**2 * np.eye(j.shape[0])
        fisher = j.T @ np.linalg.solve(c, j)
    try:
        inv = np.linalg.inv(fisher)
    except np.linalg.LinAlgError:
        return np.full(j.shape[1], np.inf)
    d = np.diag(inv)
    return np.where(d > 0, np.sqrt(np.abs(d)), np.inf)


def identified(crb_std: float, prior_log_width: float, share: float = 0.25) -> bool:
    """Whether the data identify a log parameter: its Cramer-Rao std is below ``share`` of the
    std of a uniform prior over its log box (``width / sqrt(12)``). Where it is not, the
    posterior is the prior's and the ratio posterior std / CRB says nothing about efficiency."""
    return bool(crb_std < share * prior_log_width / math.sqrt(12.0))


# ---- append-only records --------------------------------------------------------------------
def append_jsonl(path: str | os.PathLike, record: dict) -> None:
    """Append one JSON record as a line and flush it to disk: a run killed at its time limit
    keeps every record written before (records are only ever appended, never rewritten)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps(record, allow_nan=True) + "\n")
        f.flush()
        os.fsync(f.fileno())


def read_jsonl(paths: Iterable[str | os.PathLike], key: str = "index") -> list[dict]:
    """The records of every file in ``paths`` (missing files skipped), one per ``key``: a later
    file's record replaces an earlier one with the same key. A last line cut short by a kill is
    skipped; a damaged line elsewhere is an error naming the file and line. A ``.gz`` file is read
    through gzip (finished studies' records are kept compressed: the device's 64 MiB carry counts
    every tracked file)."""
    out: dict = {}
    for p in paths:
        p = Path(p)
        if not p.exists():
            continue
        if p.suffix == ".gz":
            with gzip.open(p, "rt", encoding="utf-8") as f:
                lines = f.read().splitlines()
        else:
            lines = p.read_text(encoding="utf-8").splitlines()
        for i, line in enumerate(lines, start=1):
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
            except json.JSONDecodeError as e:
                if i == len(lines):  # the write a kill cut short
                    continue
                raise ValueError(f"{p}:{i}: not a JSON record ({e})") from None
            out[rec[key]] = rec
    return [out[k] for k in sorted(out)]
