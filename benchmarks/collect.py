"""Merge result JSON files (e.g. several device runs) into one ``<machine>.json``.

    python -m benchmarks.collect experiments/results/benchmarks/h100.json run1.json run2.json ...

Sections are merged key by key (later files win); rollout rows are merged per (branches, batch)
and the top-level summary keys are recomputed from the merged rows."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from benchmarks import _common as C
from benchmarks.rollout import _merge_rows, summary


def collect(out: Path, inputs: list[Path]) -> dict:
    data: dict = {}
    for path in inputs:
        new = json.loads(Path(path).read_text())
        for key, value in new.items():
            old = data.get(key)
            if key == "rollout" and isinstance(old, dict):
                merged = {**old, **value}
                merged["rows"] = _merge_rows(
                    old.get("rows", []), value.get("rows", []), ("n_branches", "batch")
                )
                merged["trees"] = _merge_rows(
                    old.get("trees", []), value.get("trees", []), ("n_branches",)
                )
                data[key] = merged
            elif isinstance(old, dict) and isinstance(value, dict):
                data[key] = {**old, **value}
            else:
                data[key] = value
    if "rollout" in data:
        data.update(summary(data["rollout"]["rows"]))
    from treeinfer.io.atomic import atomic_write_json

    atomic_write_json(out, C._plain(data))
    return data


if __name__ == "__main__":
    collect(Path(sys.argv[1]), [Path(p) for p in sys.argv[2:]])
    print(f"wrote {sys.argv[1]}")
