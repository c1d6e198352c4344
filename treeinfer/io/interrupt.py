"""Ctrl-C that always works (issue 28, section 4).

Python runs its SIGINT handler (``KeyboardInterrupt``) only between bytecodes of the main
thread: while XLA compiles or a long MuJoCo call runs, Ctrl-C waits, and to the user it looks
swallowed. :func:`install` adds a watchdog thread woken by ``signal.set_wakeup_fd`` (written by
the C-level handler at once, whatever the main thread is doing):

- first Ctrl-C: the usual ``KeyboardInterrupt`` (the command cleans up and exits 130); if the
  process is still alive :data:`GRACE_S` seconds later, the watchdog removes the registered
  staging folders and exits 130 itself;
- second Ctrl-C: the same, at once.

Staging folders register themselves (:func:`register`, from :mod:`treeinfer.io.atomic`), so nothing
is left behind either way. An interrupted ``infer`` keeps ``RUN.partial`` on purpose (``--resume``).

The registry belongs to the :class:`CtrlC` object the command line's entry point installs as the
SIGINT handler, not to this module (no module keeps state across calls: tests/test_architecture):
:func:`register` finds it through ``signal.getsignal``, the process's own table of handlers, and
does nothing where no command line installed one (the library used from a program or a test).
"""

from __future__ import annotations

import contextlib
import os
import select
import shutil
import signal
import sys
import threading
import time

__all__ = ["GRACE_S", "CtrlC", "exit_if_interrupted", "install", "register", "unregister"]

GRACE_S = 5.0


class CtrlC:
    """The SIGINT handler of one command-line process, with the temporary folders to remove if
    the watchdog must end the process."""

    def __init__(self, grace: float = GRACE_S):
        self.grace = grace
        self._lock = threading.Lock()
        self._paths: set[str] = set()
        self._handled = 0

    def register(self, path) -> None:
        with self._lock:
            self._paths.add(os.fspath(path))

    def unregister(self, path) -> None:
        with self._lock:
            self._paths.discard(os.fspath(path))

    def hard_exit(self, msg: str) -> None:
        with self._lock:
            paths = list(self._paths)
        for p in paths:
            shutil.rmtree(p, ignore_errors=True)
        with contextlib.suppress(OSError):
            os.write(2, (msg + "\n").encode())
        os._exit(130)

    def __call__(self, signum, frame) -> None:
        """The main thread's handler: the first Ctrl-C raises KeyboardInterrupt as usual; a
        second one (e.g. while the first is being cleaned up, or during shutdown) exits at once."""
        self._handled += 1
        if self._handled >= 2:
            self.hard_exit("interrupted again: exiting now")
        raise KeyboardInterrupt

    def watch(self, fd: int) -> None:
        """The watchdog thread: reads the wakeup pipe the C-level handler writes at once."""
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
                    self.hard_exit("interrupted again: exiting now")
                deadline = time.monotonic() + self.grace
            elif deadline is not None:
                self.hard_exit(
                    f"interrupted: still busy {self.grace:g} s later (in compiled code); "
                    "exiting now"
                )


def installed() -> CtrlC | None:
    """The :class:`CtrlC` handling SIGINT in this process, if a command line installed one."""
    handler = signal.getsignal(signal.SIGINT)
    return handler if isinstance(handler, CtrlC) else None


def register(path) -> None:
    """A temporary folder to remove if the process must be ended by the watchdog."""
    if (handler := installed()) is not None:
        handler.register(path)


def unregister(path) -> None:
    if (handler := installed()) is not None:
        handler.unregister(path)


def install(grace: float = GRACE_S) -> bool:
    """Install the watchdog (once per process, from the main thread); False if it cannot be."""
    if installed() is not None:
        return True
    if threading.current_thread() is not threading.main_thread():
        return False
    handler, previous = CtrlC(grace), signal.getsignal(signal.SIGINT)
    try:
        r, w = os.pipe()
        os.set_blocking(w, False)
        signal.signal(signal.SIGINT, handler)
        signal.set_wakeup_fd(w, warn_on_full_buffer=False)
    except (OSError, ValueError):
        with contextlib.suppress(OSError, ValueError, TypeError):
            signal.signal(signal.SIGINT, previous)  # no handler without its watchdog
        return False
    threading.Thread(target=handler.watch, args=(r,), name="treeinfer-ctrl-c", daemon=True).start()
    return True


def exit_if_interrupted(rc: int) -> int:
    """``rc``, or, for an interrupted command (130) of a process whose Ctrl-C :func:`install`
    handles, the process's end at once with 130 after flushing its output. The interpreter's
    shutdown (JAX's exit hooks, threads joined) takes a while, and Python puts SIGINT back to its
    default there: a second Ctrl-C then killed the process by the signal (exit status -2) instead
    of ending it with 130. The command has cleaned up already; nothing of the shutdown is owed."""
    if rc == 130 and installed() is not None:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(rc)
    return rc
