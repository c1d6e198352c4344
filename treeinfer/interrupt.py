"""Ctrl-C that always works (issue 28, section 4).

Python runs its SIGINT handler (``KeyboardInterrupt``) only between bytecodes of the main
thread: while XLA compiles or a long MuJoCo call runs, Ctrl-C waits, and to the user it looks
swallowed. :func:`install` adds a watchdog thread woken by ``signal.set_wakeup_fd`` (written by
the C-level handler at once, whatever the main thread is doing):

- first Ctrl-C: the usual ``KeyboardInterrupt`` (the command cleans up and exits 130); if the
  process is still alive :data:`GRACE_S` seconds later, the watchdog removes the registered
  staging folders and exits 130 itself;
- second Ctrl-C: the same, at once.

Staging folders register themselves (:func:`register`, from :mod:`treeinfer._io`), so nothing is
left behind either way. An interrupted ``infer`` keeps ``RUN.partial`` on purpose (``--resume``).
"""

from __future__ import annotations

import contextlib
import os
import select
import shutil
import signal
import threading
import time

__all__ = ["GRACE_S", "install", "register", "unregister"]

GRACE_S = 5.0
_lock = threading.Lock()
_paths: set[str] = set()
_installed = False


def register(path) -> None:
    """A temporary folder to remove if the process must be ended by the watchdog."""
    with _lock:
        _paths.add(os.fspath(path))


def unregister(path) -> None:
    with _lock:
        _paths.discard(os.fspath(path))


def _hard_exit(msg: str) -> None:
    with _lock:
        paths = list(_paths)
    for p in paths:
        shutil.rmtree(p, ignore_errors=True)
    with contextlib.suppress(OSError):
        os.write(2, (msg + "\n").encode())
    os._exit(130)


def _watch(fd: int, grace: float) -> None:
    hits, deadline = 0, None
    while True:
        timeout = None if deadline is None else max(0.0, deadline - time.monotonic())
        ready, _, _ = select.select([fd], [], [], timeout)
        if ready:
            try:
                data = os.read(fd, 512)
            except OSError:
                return
            n = data.count(bytes([signal.SIGINT]))
            if not n:
                continue
            hits += n
            if hits >= 2:
                _hard_exit("interrupted again: exiting now")
            deadline = time.monotonic() + grace
        elif deadline is not None:
            _hard_exit(f"interrupted: still busy {grace:g} s later (in compiled code); exiting now")


_handled = 0


def _on_sigint(signum, frame) -> None:
    """The main thread's handler: the first Ctrl-C raises KeyboardInterrupt as usual; a second
    one (e.g. while the first is being cleaned up, or during shutdown) exits at once."""
    global _handled
    _handled += 1
    if _handled >= 2:
        _hard_exit("interrupted again: exiting now")
    raise KeyboardInterrupt


def install(grace: float = GRACE_S) -> bool:
    """Install the watchdog (once per process, from the main thread); False if it cannot be."""
    global _installed
    with _lock:
        if _installed or threading.current_thread() is not threading.main_thread():
            return _installed
        try:
            r, w = os.pipe()
            os.set_blocking(w, False)
            signal.signal(signal.SIGINT, _on_sigint)
            signal.set_wakeup_fd(w, warn_on_full_buffer=False)
        except (OSError, ValueError):
            return False
        threading.Thread(
            target=_watch, args=(r, grace), name="treeinfer-ctrl-c", daemon=True
        ).start()
        _installed = True
        return True
