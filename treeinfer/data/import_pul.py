"""Import ``.pul`` static winch pulling tests (``treeinfer import-pul``): each file becomes
``<out>/<name>.csv`` (time, force along the cable, signed tilts) and ``<out>/<name>.json`` (the
test's set-up from the metadata table, the channels, the phases and every step applied); see
:mod:`treeinfer.data.pul` (the format) and :mod:`treeinfer.data.pull_test` (the steps).

Outputs follow :mod:`treeinfer.io.ownership`: the data folder may not overlap a source or the
metadata table; same-named outputs need ``overwrite`` and are then moved aside, not deleted;
everything is read and converted before anything is written.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

from ..errors import ConfigError, TrajectoryFileError
from ..io.ownership import claim_output_files, refuse_overlap
from .pul import read_pul
from .pull_test import (
    MAX_GAP_S,
    PullTest,
    make_pull_test,
    read_test_setups,
    sha256_of,
    write_pull_test,
)

__all__ = ["METADATA_FILE", "PulImport", "find_metadata", "import_pul"]

METADATA_FILE = "trees.csv"


class PulImport(NamedTuple):
    tests: list[PullTest]
    paths: list[Path]  # the written CSV and JSON files, in pairs


def find_metadata(source: Path) -> Path | None:
    """``trees.csv`` beside the file or in the folder above it (the public data's layout:
    ``pull_tests/*.pul`` next to ``trees.csv``)."""
    for folder in (source.parent, source.parent.parent):
        if (folder / METADATA_FILE).is_file():
            return folder / METADATA_FILE
    return None


def import_pul(
    sources: Sequence[str | os.PathLike],
    out: str | os.PathLike,
    *,
    trees: str | os.PathLike | None = None,
    max_gap: float = MAX_GAP_S,
    overwrite: bool = False,
) -> PulImport:
    """Convert ``.pul`` files into ``out`` (see the module docstring).

    Args:
        sources: ``.pul`` files; each must have a row (``pul_file`` = its stem) in the metadata.
        out: the data folder (created).
        trees: the metadata table (``trees.csv``); default: found beside the first source or in
            the folder above it.
        max_gap: s; a channel is not interpolated across readings further apart (NaN there).
        overwrite: replace same-named outputs (the old ones are kept as ``NAME.old-<time>``).
    """
    sources = [Path(s) for s in sources]
    if not sources:
        raise ConfigError("import-pul: no source files given")
    if not (max_gap > 0):
        raise ConfigError(f"max_gap: must be a positive number of seconds, got {max_gap!r}")
    stems = [s.stem for s in sources]
    dup = sorted({m for m in stems if stems.count(m) > 1})
    if dup:
        raise ConfigError(f"import-pul: several sources are named {dup}; rename them")
    table = Path(trees) if trees is not None else find_metadata(sources[0])
    if table is None:
        raise ConfigError(
            f"{sources[0]}: no {METADATA_FILE} beside it or in the folder above; give the "
            "metadata table with --trees FILE"
        )
    out = Path(out)
    refuse_overlap(out, [*sources, table], "data folder")
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: exists and is not a folder")
    outputs = [out / f"{m}{suffix}" for m in stems for suffix in (".csv", ".json")]
    claim_output_files(outputs, overwrite, [*sources, table])
    setups = read_test_setups(table)
    tests = []
    for src in sources:
        setup = setups.get(src.stem)
        if setup is None:
            raise TrajectoryFileError(
                f"{src}: no row with pul_file '{src.stem}' in {table} (the test's set-up: "
                "heights, anchor, inclinometers)"
            )
        tests.append(make_pull_test(read_pul(src), setup, max_gap, sha256_of(src)))
    paths = []
    for t in tests:
        paths.extend(write_pull_test(t, out))
    return PulImport(tests, paths)
