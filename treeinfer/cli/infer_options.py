"""The options of ``treeinfer infer`` that are not argparse's: their defaults (the run
configuration's), the ones ``--resume`` takes from the checkpoint, ``--kT``'s type, and the
checks run before anything is read (moved from :mod:`treeinfer.cli.infer` to keep it under 500
lines).
"""

from __future__ import annotations

import argparse
from dataclasses import MISSING, fields
from typing import Any

from ..errors import ConfigError
from ..runs import RunConfig
from ..runs.config import OPTION_FIELDS

# Defaults of `infer` (None in argparse, so that --resume can tell which options were given):
# those of the run configuration.
INFER_DEFAULTS: dict[str, Any] = {
    f.name: f.default
    for f in fields(RunConfig)
    if f.default is not MISSING
    and f.name in OPTION_FIELDS
    and f.name not in ("grasp_fraction", "force", "model", "repair_inertia")
}
# options a resumed run takes from its checkpoint's config (argparse dest -> flag)
_RUN_OPTIONS = {
    "tree": "--tree",
    "data": "--data",
    "out": "--out",
    "sampler": "--sampler",
    "particles": "--particles",
    "iterations": "--iterations",
    "kT": "--kT",
    "seed": "--seed",
    "eta": "--eta",
    "grasp_fraction": "--grasp-fraction",
    "checkpoint_every": "--checkpoint-every",
    "force": "--force",
    "backend": "--backend",
    "prior_from": "--prior-from",
    "prior_tail": "--prior-tail",
    "allow_modified": "--allow-modified",
    "reinit_stragglers": "--reinit-stragglers",
    "drop_stragglers": "--drop-stragglers",
    "stop_when_converged": "--stop-when-converged",
    "mcmc_warmup": "--mcmc-warmup",
    "mcmc_thin": "--mcmc-thin",
    "model_kind": "--model-kind",
    "gradients": "--gradients",
    "init": "--init",
    "force_interp": "--force-interp",
    "max_sim_dt": "--max-sim-dt",
    "sim_tolerance": "--sim-tolerance",
    "likelihood": "--likelihood",
    "noise_displacement": "--noise-displacement",
    "noise_force": "--noise-force",
    "noise_velocity": "--noise-velocity",
    "model": "--model",
    "repair_inertia": "--repair-inertia",
    "tie": "--tie",
    "tie_scale": "--tie-scale",
    "shape_buckets": "--shape-buckets",
    "formats": "--formats",
    "amortised": "--amortised",
}


def _kT_arg(s: str):
    """``--kT``: a number, or ``auto`` (set from the data's noise estimate)."""
    if s.strip().lower() == "auto":
        return "auto"
    try:
        return float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a positive number or 'auto', got {s!r}"
        ) from None


def _check_meaning_changed(args: argparse.Namespace) -> None:
    """ConfigError for a command whose meaning the new defaults changed (issue 27): ``--kT``
    set the Boltzmann loss's temperature when that loss was the default."""
    if args.kT is not None and args.likelihood is None:
        raise ConfigError(
            "--kT: the default likelihood is now 'gaussian' (recorded = simulated + noise, the "
            "noise inferred; --kT has no meaning there). To keep the paper's Boltzmann loss as "
            f"before, pass --likelihood boltzmann --kT {args.kT}; or leave --kT out"
        )


def _check_infer_options(o: dict[str, Any]) -> None:
    """ConfigError naming the flag for any out-of-range option (before anything is read): the
    run configuration's own validation."""
    RunConfig(tree="", data="", out="", **o)


def check_prior_run(prior_from, allow_modified: bool | None) -> list[str]:
    """``--prior-from RUN`` checked as every reader of a run checks it, before anything else is
    read: its files against the checksums of its manifest and its parts against each other
    (:func:`treeinfer.runs.load_run`). A changed file is refused (ConfigError naming it) unless
    ``--allow-modified``; then the notes saying what changed are returned (printed, and recorded
    in the new run's config.json and summary.json). ``--allow-modified`` without
    ``--prior-from`` is refused: no run is read."""
    if prior_from is None:
        if allow_modified:
            raise ConfigError(
                "--allow-modified: infer reads a run only with --prior-from RUN; give it or "
                "leave --allow-modified out"
            )
        return []
    from ..runs import load_run

    try:
        return list(load_run(prior_from, allow_modified=bool(allow_modified)).notes)
    except ConfigError as e:
        raise ConfigError(f"--prior-from: {e}") from None
