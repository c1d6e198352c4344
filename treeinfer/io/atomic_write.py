"""Atomic file writes and the error that names the file a write failed on.

Results are written to a temporary name beside their destination and renamed into place, so an
interrupted write never leaves a half-written file. Moved here from :mod:`treeinfer.io.atomic`
(which re-exports every name) so that the modules ``_io`` builds on, :mod:`treeinfer.io.ownership`
and
:mod:`treeinfer.io.manifest`, can write files without importing ``_io`` back (an import cycle).
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from ..errors import TreeinferError

# free space (bytes) below which a writer's non-OSError failure is reported as a full disk
_NEARLY_FULL = 1 << 20

_ERRNO_HINT = {
    errno.ENOSPC: "the disk is full",
    errno.EDQUOT: "the disk quota is exceeded",
    errno.EIO: "I/O error: failing disk or lost network share?",
    errno.EROFS: "the file system is read-only",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.EBUSY: "device or resource busy (a mount point?)",
}


_DISK_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EIO, errno.EROFS)


class OutputWriteError(TreeinferError):
    """Writing an output file failed (disk full, I/O error, permissions): names the file."""


def output_error(
    path: str | os.PathLike, e: BaseException, action: str = "write"
) -> OutputWriteError:
    """An :class:`OutputWriteError` naming ``path`` for the OSError (or writer error) ``e``."""
    if isinstance(e, OSError):
        hint = _ERRNO_HINT.get(e.errno or -1)
        what = e.strerror or str(e)
        msg = (
            f"{path}: cannot {action} "
            f"({what}{'; ' + hint if hint and hint.lower() != what.lower() else ''})"
        )
    else:
        msg = f"{path}: cannot {action} ({type(e).__name__}: {e})"
        free = _free_bytes(Path(path).parent)
        if free is not None and free < _NEARLY_FULL:
            msg += f"; only {free} bytes are free on that disk: it is probably full"
    return OutputWriteError(msg)


def _free_bytes(directory: Path) -> int | None:
    try:
        return int(shutil.disk_usage(directory).free)
    except OSError:
        return None


def _is_disk_trouble(e: BaseException, directory: Path) -> bool:
    """An OSError, or a writer's own error (netCDF's "HDF error") while the disk is full."""
    if isinstance(e, OSError):
        return True
    if isinstance(e, (RuntimeError, ValueError)):
        free = _free_bytes(directory)
        return free is not None and free < _NEARLY_FULL
    return False


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _publish_mode(path, directory: bool = False) -> None:
    """mkstemp/mkdtemp create private (0600/0700) entries; results get the usual permissions."""
    os.chmod(path, (0o777 if directory else 0o666) & ~_umask())


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` via a temporary file + ``os.replace``."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as e:
        raise output_error(path, e) from None
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        _publish_mode(tmp)
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(e, OSError):
            raise output_error(path, e) from None
        raise
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj: Any) -> Path:
    return atomic_write_text(
        path, json.dumps(obj, indent=2, sort_keys=True, default=_json_default) + "\n"
    )


@contextlib.contextmanager
def atomic_save(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path for a writer that insists on a file name
    (``fig.savefig``, ``InferenceData.to_netcdf``); rename it into place on success."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
        os.close(fd)
    except OSError as e:
        raise output_error(path, e) from None
    try:
        yield Path(tmp)
        _publish_mode(tmp)
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if (
            not isinstance(e, TreeinferError)
            and isinstance(e, Exception)
            and _is_disk_trouble(e, path.parent)
        ):
            raise output_error(path, e) from e
        raise


def _json_default(o: Any):
    import numpy as np

    if isinstance(o, (np.generic,)):
        return o.item()
    if hasattr(o, "tolist"):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
