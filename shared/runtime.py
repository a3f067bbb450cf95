"""What every service process does at start: logging, a shutdown event set by SIGINT/SIGTERM."""

from __future__ import annotations

import logging
import signal
import threading


def setup_logging(level: str, name: str) -> logging.Logger:
    """Log lines as ``time level service: message`` on stderr."""
    logging.basicConfig(level=level.upper(), format=f"%(asctime)s %(levelname)s {name}: %(message)s")
    return logging.getLogger(name)


def shutdown_event() -> threading.Event:
    """An event set on SIGINT or SIGTERM; long loops wait on it instead of sleeping."""
    stop = threading.Event()

    def handler(signum: int, frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop
