"""What a new run reads from disk, once per command: the run's tree (``--model``, the static
model's stiffness-only tree, ``--tie``), the training trajectories, the data folder's true
parameters and the data files' manifest."""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..data.trajectories import TRUE_PARAMS_FILE, Trajectory, read_trajectory_dir
from ..data.trajectories import read_true_params as read_true_params_file
from ..errors import ConfigError
from ..io.provenance import data_manifest
from ..tree.description import Tree, load_tree


def load_run_tree(tree_path, model=None, repair_inertia=None) -> Tree:
    """The tree of a run: the tree file, with ``--model``/``--repair-inertia`` applied to its
    ``model:`` section (:func:`treeinfer.tree.usermodel.attach_model`; the file's sha256
    recorded)."""
    tree = load_tree(tree_path)
    if model is not None or repair_inertia is not None or tree.model is not None:
        from ..tree.usermodel import attach_model

        tree = attach_model(tree, model, repair_inertia)
    return tree


class RunInputs(NamedTuple):
    """What a new run reads from disk, read once per command (:func:`load_run_inputs`) and passed
    to :func:`infer_config` and :func:`treeinfer.runs.run_inference`.

    Attributes: tree (the run's tree: ``--model`` attached, stiffness only for the static model);
    trajectories (the training data, in file order); truth (``[2R]`` natural units from the data
    folder's ``true_params.json``, or None); files (the data files' names and sha256,
    :func:`~.provenance.data_manifest`); channels (the folder's observation channels besides the
    grasp point, :func:`treeinfer.data.channels.read_channels`, checked against the tree and the
    pulls; () without a ``channels.yaml``)."""

    tree: Tree
    trajectories: list[Trajectory]
    truth: np.ndarray | None
    files: list[dict]
    channels: tuple = ()


def load_run_inputs(
    tree_path: str | os.PathLike,
    data_dir: str | os.PathLike,
    model: str | os.PathLike | None = None,
    repair_inertia: str | None = None,
    model_kind: str = "dynamic",
    tie: str | None = None,
    tie_scale: float | None = None,
) -> RunInputs:
    """Read the tree and the training data of a new run once (clear errors for a missing folder,
    a bad file or a bad tree)."""
    from ..inference.static import run_tree

    data_dir = Path(data_dir)
    from ..inference.static import with_tie

    tree = run_tree(load_run_tree(tree_path, model, repair_inertia), model_kind)
    tree = with_tie(tree, tie, tie_scale)  # --tie/--tie-scale over the file's inference.tie
    files = data_manifest(data_dir) if data_dir.is_dir() else []
    trajs = read_trajectory_dir(data_dir)
    from ..data.channels import read_channels

    channels = read_channels(data_dir, tree, trajs)
    return RunInputs(tree, trajs, read_true_params(tree, data_dir), files, channels)


def read_true_params(tree: Tree, data_dir: str | os.PathLike) -> np.ndarray | None:
    """True parameters ``[2R]`` (natural units, label order) from ``DIR/true_params.json``.

    None if there is no such file."""
    path = Path(data_dir) / TRUE_PARAMS_FILE
    if not path.is_file():
        return None
    return read_true_params_file(tree, path, where=f"--params-json {path}")


def check_data_unchanged(config: dict) -> list[Trajectory]:
    """Re-read the run's training data, refusing if any file changed, vanished or appeared."""
    d = Path(config["data"]["dir"])
    if not d.is_dir():
        raise ConfigError(f"{d}: the run's data folder no longer exists; restore it to resume")
    from ..data.channel_files import channel_manifest

    # the pulls and, where the run had them, its observation channels (channels.yaml + files)
    channels = config["data"].get("channel_files") or []
    now = {f["name"]: f["sha256"] for f in data_manifest(d)}
    then = {f["name"]: f["sha256"] for f in config["data"]["files"]}
    now.update({f["name"]: f["sha256"] for f in (channel_manifest(d) if channels else [])})
    then.update({f["name"]: f["sha256"] for f in channels})
    changed = sorted(n for n in then if n in now and now[n] != then[n])
    missing = sorted(set(then) - set(now))
    added = sorted(set(now) - set(then))
    if changed or missing or added:
        parts = (
            ([f"changed: {', '.join(changed)}"] if changed else [])
            + ([f"missing: {', '.join(missing)}"] if missing else [])
            + ([f"new: {', '.join(added)}"] if added else [])
        )
        raise ConfigError(
            f"{d}: the training data differ from the run's (sha256 in config.json; "
            f"{'; '.join(parts)}); restore the original files, or start a new run without "
            "--resume"
        )
    return read_trajectory_dir(d)
