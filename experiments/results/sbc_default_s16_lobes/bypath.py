"""SBC coverage by the path each fit took: importance weights trusted at k_hat < 0.35, at
0.35-0.5, or resample-move. Usage: ``bypath.py DIR``."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paired import load, stats  # noqa: E402


def path_of(rec) -> str:
    if "resample-move" in (rec.get("stop_reason") or ""):
        return "resample-move"
    khat = rec.get("khat")
    if khat is None or khat > 0.5:
        return "other"
    return "importance k_hat < 0.35" if khat < 0.35 else "importance k_hat 0.35-0.5"


def main(folder):
    groups = {}
    for rec in load(folder).values():
        groups.setdefault(path_of(rec), []).append(stats(rec))
    for name, rows in groups.items():
        inside = np.array([r[0] for r in rows])[:, :-1]  # the gains (sigma_x last)
        z = np.array([r[1] for r in rows])[:, :-1]
        print(
            f"{name}: {len(rows)} sets, 95% coverage of the gains {inside.mean():.3f} "
            f"({np.round(inside.mean(0), 2)}), rms z {np.sqrt((z**2).mean()):.2f}, "
            f"median |z| {np.median(np.abs(z)):.2f}"
        )


if __name__ == "__main__":
    main(sys.argv[1])
