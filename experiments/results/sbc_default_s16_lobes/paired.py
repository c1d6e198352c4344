"""Paired SBC comparison of two folders of records (``records_w*.jsonl[.gz]``) on their common
data sets: 95% coverage and rms z per parameter, fits with some |z| > 5 / > 10, and the data
sets whose worst |z| changed. Usage: ``paired.py DIR_A DIR_B``."""

import glob
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
from experiments._study_stats import read_jsonl  # noqa: E402


def load(folder):
    files = sorted(glob.glob(folder + "/records_w*.jsonl*"))
    return {r["index"]: r for r in read_jsonl(files) if "draws" in r}


def stats(rec):
    """(inside the central 95% interval [P], z [P]) of the truth in one record."""
    draws = np.asarray(rec["draws"])
    truth = np.array([rec["truth"][name] for name in rec["labels"]])
    lo, hi = np.quantile(draws, [0.025, 0.975], axis=0)
    return (truth >= lo) & (truth <= hi), (truth - draws.mean(0)) / draws.std(0)


def main(a_dir, b_dir):
    a, b = load(a_dir), load(b_dir)
    common = sorted(set(a) & set(b))
    for name, recs in (("A", a), ("B", b)):
        inside = np.array([stats(recs[i])[0] for i in common])
        z = np.array([stats(recs[i])[1] for i in common])
        worst = np.abs(z).max(1)
        print(
            f"{name} n {len(common)} 95% cov {np.round(inside.mean(0), 2)} "
            f"rms z {np.round(np.sqrt((z**2).mean(0)), 2)} "
            f"|z|>5: {int((worst > 5).sum())} >10: {int((worst > 10).sum())}"
        )
    print("worst |z| (A -> B) where either > 4:")
    for i in common:
        za, zb = (float(np.abs(stats(r[i])[1]).max()) for r in (a, b))
        if max(za, zb) > 4:
            print(f"  {i}: {za:.1f} -> {zb:.1f}")
    walls = [np.median([r[i]["wall_s"] for i in common]) for r in (a, b)]
    print("median wall", [round(w) for w in walls])


if __name__ == "__main__":
    main(*sys.argv[1:3])
