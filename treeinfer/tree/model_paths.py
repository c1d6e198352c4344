"""Every file MuJoCo would open for a user's URDF/MJCF, checked before MuJoCo opens any.

MuJoCo reads ``<include file=...>`` and the ``file=`` of meshes, textures, height fields and
skins (URDF: ``<mesh filename=...>``) itself, with blocking reads: a FIFO there hangs the
command, ``/dev/zero`` fills memory, a symbolic-link loop gives an unhelpful error. This module
walks the model (includes recursively, each file once, at most :data:`MAX_INCLUDE_DEPTH` deep),
resolves each path as MuJoCo does (relative to the main model's folder, through the compiler's
``meshdir``/``texturedir``/``assetdir``) and refuses, naming the file that refers to it, any
that is not a regular file; nothing is opened but the XML files themselves, through
:func:`treeinfer.io.safe_load.read_regular_file` (non-blocking open, size limit).

A path that does not exist is left to MuJoCo, whose message names it.
"""

from __future__ import annotations

import errno
import os
import xml.etree.ElementTree as ET
from pathlib import Path

from ..errors import TreeFileError
from ..io.safe_load import _kind_of, read_regular_file

__all__ = ["MAX_INCLUDE_DEPTH", "check_model_paths"]

MAX_INCLUDE_DEPTH = 16
# elements whose ``file`` attribute names an asset (MJCF), and URDF's mesh ``filename``
_ASSET_TAGS = {"mesh": "meshdir", "texture": "texturedir", "hfield": "meshdir", "skin": "meshdir"}


def _refuse_special(path: Path, referrer: str) -> None:
    """Raise for a path that exists and is not a regular file, or that loops; never opens it."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return  # MuJoCo names the missing file itself
    except OSError as e:
        why = "a symbolic-link loop" if e.errno == errno.ELOOP else (e.strerror or str(e))
        raise TreeFileError(f"{referrer}: {path} cannot be used ({why})") from None
    kind = _kind_of(st.st_mode)
    if kind is not None:
        raise TreeFileError(f"{referrer}: {path} is {kind}, not a regular file; refused")


def _parse(path: Path) -> ET.Element:
    raw = read_regular_file(path, "model file", TreeFileError)
    try:
        return ET.fromstring(raw)  # expat >= 2.4 limits entity expansion (billion laughs)
    except ET.ParseError as e:
        raise TreeFileError(f"{path}: not valid XML ({e})") from None


def check_model_paths(path: str | os.PathLike) -> list[Path]:
    """Check the model file ``path`` and every file it refers to (see the module docstring).

    Returns the files checked. Raises :class:`TreeFileError` naming the referring file.
    """
    path = Path(path)
    root_dir = path.parent
    dirs: dict[str, Path] = {}
    seen: set[Path] = set()
    checked: list[Path] = []
    stack: list[tuple[Path, int, str]] = [(path, 0, str(path))]
    while stack:  # iterative: an include chain cannot exhaust Python's recursion limit
        p, depth, referrer = stack.pop()
        _refuse_special(p, referrer)
        real = Path(os.path.realpath(p))
        if real in seen:
            continue
        if depth > MAX_INCLUDE_DEPTH:
            raise TreeFileError(
                f"{referrer}: <include> nested more than {MAX_INCLUDE_DEPTH} deep (a loop?)"
            )
        seen.add(real)
        checked.append(p)
        if not p.exists():
            continue
        tree = _parse(p)
        for el in tree.iter("compiler"):
            for key in ("meshdir", "texturedir", "assetdir"):
                if el.get(key):
                    dirs[key] = root_dir / el.get(key)
        for el in tree.iter():
            tag = el.tag if isinstance(el.tag, str) else ""
            if tag == "include" and el.get("file"):
                stack.append((root_dir / el.get("file"), depth + 1, f"{p}: <include>"))
            elif tag in _ASSET_TAGS and el.get("file"):
                base = dirs.get(_ASSET_TAGS[tag]) or dirs.get("assetdir") or root_dir
                f = Path(el.get("file"))
                _refuse_special(f if f.is_absolute() else base / f, f"{p}: <{tag}>")
            elif tag == "mesh" and el.get("filename"):  # URDF
                name = el.get("filename")
                name = name.split("://", 1)[1] if "://" in name else name
                f = Path(name)
                _refuse_special(f if f.is_absolute() else root_dir / f, f"{p}: <mesh>")
    return checked
