"""What every service process does at start: logging, a shutdown event set by SIGINT/SIGTERM;
and what a process that starts others gives them: death with their parent; and a wait for a
process that is not its child to end (the launchers' guards)."""

from __future__ import annotations

import ctypes
import logging
import os
import select
import signal
import threading

try:  # looked up here, not in the forked child, where only async-signal-safe work belongs
    _prctl = ctypes.CDLL("libc.so.6", use_errno=True).prctl
except (OSError, AttributeError):  # not Linux: Ctrl-C and run/done still stop the services
    _prctl = None


def die_with_parent() -> None:
    """In a child, before exec: get SIGTERM when its parent dies (even by SIGKILL), so no child outlives it."""
    if _prctl is not None:
        _prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG


def wait_for_exit(pid: int) -> None:
    """Return once process ``pid`` (not a child of this one) has ended, at once if it has already."""
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        return
    select.select([fd], [], [])
    os.close(fd)


def setup_logging(level: str, name: str) -> logging.Logger:
    """Log lines as ``time level service: message`` on stderr; with ``RUST_LOG`` set (e.g.
    ``RUST_LOG=zenoh=debug``), Zenoh's own log too."""
    logging.basicConfig(level=level.upper(), format=f"%(asctime)s %(levelname)s {name}: %(message)s")
    if os.environ.get("RUST_LOG"):
        import zenoh

        zenoh.init_log_from_env_or("error")
    return logging.getLogger(name)


SHUTDOWN: threading.Event | None = None  # the process's, once shutdown_event() made it


class Stopped(Exception):
    """The process was stopped (SIGINT, SIGTERM) while it waited for something that does not
    look at its shutdown event itself (a Zenoh session opening)."""


def shutdown_event() -> threading.Event:
    """An event set on SIGINT or SIGTERM; long loops wait on it instead of sleeping.

    The handler takes no lock: it writes a byte to a pipe, and a thread of its own sets the event.
    (A handler runs on the main thread between two of its steps, possibly while that thread holds
    the event's lock, in ``stop.wait()`` or in a handler interrupted by the next signal: setting
    the event there deadlocked a service sent two SIGTERMs at once, for good.)"""
    global SHUTDOWN
    stop = SHUTDOWN = threading.Event()
    read_end, write_end = os.pipe()
    os.set_blocking(write_end, False)

    def watch() -> None:
        os.read(read_end, 1)
        stop.set()

    threading.Thread(target=watch, name="shutdown", daemon=True).start()

    def handler(signum: int, frame: object) -> None:
        try:
            os.write(write_end, b"\0")
        except BlockingIOError:  # the pipe is full: the event is being set already
            pass

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop
