"""The checks of a run folder a checksum cannot make (moved from :mod:`treeinfer.io.manifest`,
which sits below the tree and the run layer, so that the manifest no longer imports them).

:func:`check_run_consistency` covers an old run without a manifest, or one let through with
``--allow-modified``, whose tree.yaml is not the tree config.json recorded, whose particles do not
fit their labels, or whose summary.json contradicts its particles.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Mapping
from pathlib import Path

from ..errors import ConfigError

__all__ = ["check_run_consistency"]


def check_run_consistency(
    run_dir: str | os.PathLike,
    config: Mapping,
    tree,
    theta,
    labels: Iterable[str],
    summary: Mapping,
    allow_modified: bool = False,
) -> list[str]:
    """Checks a checksum cannot make (a run from before manifests, or one let through with
    ``--allow-modified``): tree.yaml is the tree config.json recorded; the particles have one
    column per label; summary.json's posterior table is the particles' (same labels, the same
    mean of each gain over the stable particles). Raises ConfigError naming the file, or with
    ``allow_modified`` returns notes."""
    import numpy as np

    from ..io.provenance import tree_to_dict_json
    from ..tree.description import tree_to_dict

    run_dir = Path(run_dir)
    labels = list(labels)
    problems = []
    if tree_to_dict_json(tree_to_dict(tree)) != tree_to_dict_json(config["tree_dict"]):
        problems.append(
            f"{run_dir / 'tree.yaml'}: is not the tree recorded in config.json (swapped or edited)"
        )
    theta = np.asarray(theta, float)
    if theta.ndim != 2 or theta.shape[1] != len(labels):
        problems.append(
            f"{run_dir / 'trace.npz'}: particles of shape {theta.shape} for {len(labels)} "
            f"labels {labels}"
        )
    table = summary.get("posterior") if isinstance(summary, Mapping) else None
    if isinstance(table, Mapping) and table and not problems:
        if sorted(table) != sorted(labels):
            problems.append(
                f"{run_dir / 'summary.json'}, field 'posterior': labels {list(table)} are not "
                f"the particles' {labels}"
            )
        else:
            bad = set(summary.get("unstable_particles") or [])
            ok = np.all(np.isfinite(theta), axis=1)
            ok &= np.array([i not in bad for i in range(len(theta))], bool)
            for j, lab in enumerate(labels):
                rec = table[lab]
                if not (lab.startswith(("Kp[", "Kd[")) and isinstance(rec, Mapping)):
                    continue
                mean = rec.get("mean")
                if not isinstance(mean, (int, float)) or ok.sum() < 2:
                    continue
                now = float(np.mean(np.exp(theta[ok, j])))
                if not math.isclose(now, float(mean), rel_tol=1e-3, abs_tol=1e-12):
                    problems.append(
                        f"{run_dir / 'summary.json'}, field 'posterior.{lab}.mean': {mean!r} "
                        f"contradicts the particles (their mean is {now:.6g})"
                    )
    if not problems:
        return []
    if not allow_modified:
        raise ConfigError(
            f"{problems[0]}{'; ' + '; '.join(problems[1:]) if problems[1:] else ''}; the run "
            "folder does not hold together: run infer again, or pass --allow-modified to use it "
            "anyway (recorded in the output)"
        )
    return [f"{run_dir}: used with --allow-modified although {p}" for p in problems]
