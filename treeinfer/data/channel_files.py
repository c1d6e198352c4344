"""Writing observation channels (:mod:`treeinfer.data.channels`) and listing their files for
checksums: ``channels.yaml`` + ``channels/<name>.csv`` in SI units, and the manifest a run
records so that a changed channel file is noticed on ``--resume``."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from .channels import CHANNELS_FILE, SI_UNIT, Channel


def channel_to_dict(ch: Channel, file: str) -> dict:
    """The ``channels.yaml`` entry of ``ch`` with its values written to ``file`` in SI units."""
    p = {"link": ch.point.link}
    p.update({"fraction": ch.point.fraction} if ch.point.fraction is not None else {})
    p.update({"distance": ch.point.distance} if ch.point.distance is not None else {})
    return {
        "name": ch.name,
        "recording": ch.recording,
        "file": file,
        "kind": ch.kind,
        "point": p,
        "components": list(ch.components),
        "units": {"time": "s", "value": SI_UNIT[ch.kind]},
        "time_offset": 0.0,
        "noise": "auto" if ch.noise is None else float(ch.noise),
        **({"camera": camera_to_dict(ch.camera)} if ch.camera else {}),
        **({"sensor": ch.sensor} if ch.sensor else {}),
    }


def camera_to_dict(camera: tuple) -> dict:
    """The ``channels.yaml`` form of :func:`parse_camera`'s tuple."""
    c = [float(x) for x in camera]
    return {"focal": c[0:2], "center": c[2:4], "rotation": [c[4:7], c[7:10], c[10:13]],
            "position": c[13:16]}  # fmt: skip


def write_channels(folder: str | os.PathLike, channels: Sequence[Channel]) -> Path:
    """Write ``channels`` (SI, on the pulls' clock) as ``channels.yaml`` + ``channels/*.csv``."""
    import yaml

    folder = Path(folder)
    (folder / "channels").mkdir(parents=True, exist_ok=True)
    entries = []
    for ch in channels:
        rel = f"channels/{ch.name}.csv"
        data = np.column_stack([ch.time, ch.values])
        header = ",".join(["time", *ch.components])
        np.savetxt(folder / rel, data, delimiter=",", header=header, comments="", fmt="%.9g")
        entries.append(channel_to_dict(ch, rel))
    path = folder / CHANNELS_FILE
    path.write_text(yaml.safe_dump({"channels": entries}, sort_keys=False))
    return path


def channel_files(folder: str | os.PathLike) -> list[Path]:
    """``channels.yaml`` and the channel files it names (those that exist), for checksums;
    [] without a ``channels.yaml``. Reads the YAML only, no validation."""
    import yaml

    folder = Path(folder)
    path = folder / CHANNELS_FILE
    if not path.is_file():
        return []
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError:
        return [path]
    entries = raw.get("channels") if isinstance(raw, dict) else None
    files = [e.get("file") for e in entries or [] if isinstance(e, dict)]
    named = sorted({folder / f for f in files if isinstance(f, str) and (folder / f).is_file()})
    return [path, *named]


def channel_manifest(folder: str | os.PathLike) -> list[dict]:
    """``[{name, sha256, bytes}]`` of :func:`channel_files` (names relative to the folder), as
    :func:`treeinfer.io.provenance.data_manifest` lists the pulls; [] without channels."""
    from ..io.provenance import file_sha256

    folder = Path(folder)
    return [
        {"name": p.relative_to(folder).as_posix(), "sha256": file_sha256(p),
         "bytes": p.stat().st_size}
        for p in channel_files(folder)
    ]  # fmt: skip
