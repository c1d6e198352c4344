"""Two SBC runs of ``sbc_default.py`` on the same data sets (same ``--seed``, so data set ``i``
is the same truth and data in both), compared pair by pair: per parameter the rms of the
truths' z-scores ``(truth - posterior mean) / posterior sd`` (1 when calibrated, larger when the
intervals are too narrow or off centre), the share of truths inside the central 95% interval of
the draws, and the median wall time per fit.

    python experiments/sbc_paired.py experiments/results/sbc_default_h200 \
        experiments/results/sbc_default_h200_khat05
"""

from __future__ import annotations

import argparse
import glob
import json

import numpy as np


def load(folder: str) -> dict:
    """``{index: record}`` of the ranked (non-failed) data sets in ``folder/records*.jsonl``."""
    recs = [json.loads(x) for f in sorted(glob.glob(f"{folder}/records*.jsonl")) for x in open(f)]
    return {r["index"]: r for r in recs if "draws" in r}


def compare(records: dict, indices) -> dict:
    """rms z-score, 95% coverage per parameter (log units, as the draws are stored), median wall."""
    labels = records[indices[0]]["labels"]
    z, inside = [], []
    for i in indices:
        d = np.asarray(records[i]["draws"], float)
        t = np.array([records[i]["truth"][k] for k in labels])
        z.append((t - d.mean(0)) / d.std(0))
        lo, hi = np.quantile(d, [0.025, 0.975], axis=0)
        inside.append((lo <= t) & (t <= hi))
    return {
        "labels": labels,
        "rms_z": np.sqrt(np.mean(np.square(z), axis=0)).round(2).tolist(),
        "cover_95": np.mean(inside, axis=0).round(2).tolist(),
        "wall_s_median": float(np.median([records[i]["wall_s"] for i in indices])),
    }


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("before")
    ap.add_argument("after")
    args = ap.parse_args(argv)
    a, b = load(args.before), load(args.after)
    common = sorted(set(a) & set(b))
    if not common:
        raise SystemExit("no data set is in both runs")
    out = {
        "paired_data_sets": len(common),
        "before": compare(a, common),
        "after": compare(b, common),
    }
    print(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
