"""The results table of ``treeinfer batch``: one row per manifest item, written as
``results.csv`` and, when pyarrow is installed, ``results.parquet`` (both atomically).

Columns (:data:`COLUMNS`, then three per posterior parameter, in the order they first appear):

- ``id``, ``status`` (``done``: the run folder is written, ``failed``: the item raised (its
  ``error``), ``invalid``: the manifest row is unusable, ``interrupted``, ``pending``: not run);
  ``fit_verdict`` (``ok`` | ``warning`` | ``poor_fit``, summary.json's ``fit``);
  ``n_warnings`` (convergence warnings + fit-check reasons + data-check findings) and
  ``warnings`` (the same, joined by `` | ``);
- ``test_coverage_pct``: % of the held-out recorded displacement points inside the 95%
  predictive band (nominal 95; only when the item gives ``test``), ``test_band_width_mm``,
  ``test_nll_per_point`` (nats), ``n_test_points``;
- ``seconds_total`` (the item in its worker), ``seconds_infer``, ``seconds_test``;
  ``xla_compiles`` and ``compile_seconds``: XLA programs the item compiled (not loaded from the
  persistent cache) and the time that took (0 for an item whose shapes its worker has seen);
  ``started_utc``, ``finished_utc``, ``worker`` (host:pid), ``reused`` (true: taken from an
  earlier batch run, not recomputed);
- ``run_dir`` (``runs/ID``, inside the batch folder), ``tree``, ``recordings``, ``test``,
  ``manifest_line``, ``error``;
- per parameter ``LABEL_mean``, ``LABEL_lower``, ``LABEL_upper``: the posterior mean and 95%
  interval in natural units (Kp N m/rad, Kd N m s/rad, sigma_x m), as summary.json's
  ``posterior`` table.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from pathlib import Path

from ..io.atomic_write import atomic_save, atomic_write_text

COLUMNS = (
    "id",
    "status",
    "fit_verdict",
    "n_warnings",
    "test_coverage_pct",
    "test_band_width_mm",
    "test_nll_per_point",
    "n_test_points",
    "seconds_total",
    "seconds_infer",
    "seconds_test",
    "xla_compiles",
    "compile_seconds",
    "started_utc",
    "finished_utc",
    "worker",
    "reused",
    "run_dir",
    "tree",
    "recordings",
    "test",
    "manifest_line",
    "error",
    "warnings",
)
_INTS = {"n_warnings", "n_test_points", "manifest_line", "xla_compiles"}
_BOOLS = {"reused"}
_FLOATS = {
    "test_coverage_pct",
    "test_band_width_mm",
    "test_nll_per_point",
    "seconds_total",
    "seconds_infer",
    "seconds_test",
    "compile_seconds",
}
STAT_SUFFIXES = ("_mean", "_lower", "_upper")


def columns(rows: Sequence[dict]) -> list[str]:
    """:data:`COLUMNS`, then the parameter columns of ``rows`` in the order they appear."""
    out = list(COLUMNS)
    seen = set(out)
    for r in rows:
        for k in r:
            if k not in seen and k.endswith(STAT_SUFFIXES):
                seen.add(k)
                out.append(k)
    return out


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "" if not math.isfinite(v) else repr(v)
    return str(v)


def csv_text(rows: Sequence[dict]) -> str:
    cols = columns(rows)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for r in rows:
        w.writerow([_cell(r.get(c)) for c in cols])
    return buf.getvalue()


def _arrow_table(rows: Sequence[dict]):
    import pyarrow as pa

    cols = columns(rows)

    def kind(c):
        if c in _INTS:
            return pa.int64()
        if c in _BOOLS:
            return pa.bool_()
        if c in _FLOATS or c.endswith(STAT_SUFFIXES):
            return pa.float64()
        return pa.string()

    schema = pa.schema([(c, kind(c)) for c in cols])
    data = {c: [r.get(c) for r in rows] for c in cols}
    return pa.Table.from_pydict(data, schema=schema)


def write_table(out: Path, rows: Sequence[dict]) -> list[str]:
    """Write ``out/results.csv`` and (pyarrow installed) ``out/results.parquet``; return the
    names written, and a note when Parquet was left out."""
    out = Path(out)
    atomic_write_text(out / "results.csv", csv_text(rows))
    try:
        import pyarrow.parquet as pq
    except ImportError:
        return [
            "results.csv",
            "(no results.parquet: pyarrow is not installed; pip install pyarrow)",
        ]
    table = _arrow_table(rows)
    with atomic_save(out / "results.parquet") as tmp:
        pq.write_table(table, tmp)
    return ["results.csv", "results.parquet"]
