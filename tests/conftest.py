"""Shared fixtures: free loopback ports, Zenoh settings for isolated test sessions, kit data."""

from __future__ import annotations

import os
import socket
import sys
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import pytest

from swarmmap.shared.config import ZenohSettings

REPO = Path(__file__).resolve().parents[1]
KIT_DATA = REPO.parent / "shared" / "data"
SWARMMAP = [sys.executable, "-m", "swarmmap.services.cli"]  # the `swarmmap` command of this interpreter


def clean_env() -> dict[str, str]:
    """This process's environment without SWARMMAP_* settings, for a service under test."""
    return {k: v for k, v in os.environ.items() if not k.startswith("SWARMMAP_")}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(predicate: Callable[[], bool], timeout: float, interval: float = 0.05) -> bool:
    """Poll ``predicate`` until it holds or ``timeout`` passes (no fixed sleeps in tests)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval)
    return predicate()


@pytest.fixture
def run_id() -> str:
    return "t" + uuid.uuid4().hex[:10]


@pytest.fixture
def zenoh_pair() -> tuple[ZenohSettings, ZenohSettings]:
    """Settings for two peers on loopback: one listens on a free port, the other connects to it
    (insecure: these tests are of the transport; tests/shared/test_security.py checks the secure one)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    a = ZenohSettings(mode="peer", listen=[endpoint], multicast_scouting=False, insecure=True)
    b = ZenohSettings(mode="peer", connect=[endpoint], listen=["tcp/127.0.0.1:0"], multicast_scouting=False, insecure=True)
    return a, b


def recording_entities(path: Path) -> dict[str, set[str]]:
    """Entity path -> timeline names of everything in a Rerun ``.rrd`` (read with Rerun's own reader)."""
    from rerun.chunk import RrdReader

    timelines: dict[str, set[str]] = {}
    for chunk in RrdReader(path).stream():
        timelines.setdefault(chunk.entity_path, set()).update(chunk.timeline_names)
    return timelines
