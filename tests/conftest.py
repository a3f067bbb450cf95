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

from swarmmap.shared.run.config import ZenohSettings

REPO = Path(__file__).resolve().parents[1]
KIT_DATA = REPO.parent / "shared" / "data"
SWARMMAP = [sys.executable, "-m", "swarmmap.services.cli"]  # the `swarmmap` command of this interpreter
# A command that must answer without waiting on the run (a refusal, a finished run's status) does
# so well within this on a loaded machine; the waits it replaces were 30-60 s. The goal, 10 s, is
# measured by bench/refusals.py.
PROMPT_S = 30.0


# `make test-unit`: the tests that start no process and open no socket (no Zenoh session, no
# service); a test that tries is stopped with a message saying to mark it `integration`.
UNIT_TIER = os.environ.get("SWARMMAP_TEST_TIER") == "unit"


class NotAUnitTest(RuntimeError):
    """Raised in the unit tier by whatever starts a process or opens a socket."""


@pytest.fixture(autouse=True)
def _unit_tier_starts_no_process_and_opens_no_socket(monkeypatch):
    if not UNIT_TIER:
        yield
        return
    import multiprocessing.process
    import subprocess

    import zenoh

    def refuse(what: str):
        def refused(*args, **kwargs):
            raise NotAUnitTest(f"the unit tier (make test-unit) {what}: mark this test (or its module) "
                               "pytest.mark.integration")
        return refused

    monkeypatch.setattr(subprocess.Popen, "__init__", refuse("starts no process"))
    monkeypatch.setattr(multiprocessing.process.BaseProcess, "start", refuse("starts no process"))
    monkeypatch.setattr(os, "fork", refuse("starts no process"))
    for method in ("bind", "connect", "connect_ex"):
        monkeypatch.setattr(socket.socket, method, refuse("opens no socket"))
    monkeypatch.setattr(zenoh, "open", refuse("opens no Zenoh session"))
    yield


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """Under CI (``CI=true``) a test skipped for missing kit data fails: a green CI ran them all."""
    outcome = yield
    report = outcome.get_result()
    if report.skipped and os.environ.get("CI") == "true" and isinstance(report.longrepr, tuple) \
            and "kit data" in str(report.longrepr[2]):
        report.outcome = "failed"
        report.longrepr = f"CI=true and the kit is incomplete: {report.longrepr[2]}"


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
    (insecure: these tests are of the transport; tests/shared/wire/test_secrets.py checks the secure one)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    a = ZenohSettings(mode="peer", listen=[endpoint], multicast_scouting=False, insecure=True)
    b = ZenohSettings(mode="peer", connect=[endpoint], listen=["tcp/127.0.0.1:0"], multicast_scouting=False, insecure=True)
    return a, b


def recorded_run(run_dir: Path, ok: bool = True, losses: tuple[float, ...] = (0.1250, 0.2350), rounds: int = 60,
                 run_id: str = "demo-1", model: str = "fourier") -> Path:
    """A finished run directory as the recorder writes it (its own MetricsRecorder and summary):
    config.yaml, metrics.csv with rounds 0, 30 and ``rounds`` of one learner per loss,
    summary.json, an empty recording.rrd, models/ and logs/."""
    import json

    from swarmmap.services.recorder import MetricsRecorder, summary
    from swarmmap.shared.run.config import resolve
    from swarmmap.shared.wire.protocol import Metrics

    run_dir.mkdir(parents=True)
    cfg = resolve({"preset": "smoke", "run_id": run_id, "robots": len(losses), "run_dir": str(run_dir),
                   "learner": {"rounds": rounds, "model": model}}, environ={})
    (run_dir / "config.yaml").write_text(cfg.dump_yaml())
    rec = MetricsRecorder(run_dir / "metrics.csv")
    for k, fraction in ((0, 0.0), (rounds // 2, 0.5), (rounds, 1.0)):
        for robot, val in enumerate(losses):
            rec.add(Metrics(run=run_id, sender=robot, round=k, wall_time_s=20.0 * fraction, val_bce=0.7 + (val - 0.7) * fraction,
                            consensus_error=0.0, bytes_sent=int(2_500_000 * fraction), bytes_received=0, final=ok and k == rounds))
    rec.close()
    doc = summary(cfg, rec, ok, f"all {len(losses)} learners finished" if ok else "learner 1 left before finishing", 42.0)
    (run_dir / "summary.json").write_text(json.dumps(doc))
    (run_dir / "recording.rrd").write_bytes(b"")
    (run_dir / "models").mkdir()
    (run_dir / "logs").mkdir()
    return run_dir


def recording_entities(path: Path) -> dict[str, set[str]]:
    """Entity path -> timeline names of everything in a Rerun ``.rrd`` (read with Rerun's own reader)."""
    from rerun.chunk import RrdReader

    timelines: dict[str, set[str]] = {}
    for chunk in RrdReader(path).stream():
        timelines.setdefault(chunk.entity_path, set()).update(chunk.timeline_names)
    return timelines


@pytest.fixture
def tmpfs(tmp_path):
    """``tmpfs(size, read_only=False)``: a fresh tmpfs of ``size`` (e.g. ``"200k"``) mounted under
    ``tmp_path``, unmounted at the end; skips where this user may not mount (only root may)."""
    import subprocess

    mounted: list[Path] = []

    def mount(size: str, read_only: bool = False) -> Path:
        point = tmp_path / f"tmpfs-{len(mounted)}"
        point.mkdir()
        opts = f"size={size}" + (",ro" if read_only else "")
        proc = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(point)], capture_output=True, text=True)
        if proc.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {proc.stderr.strip() or proc.returncode}")
        mounted.append(point)
        return point

    yield mount
    for point in reversed(mounted):
        subprocess.run(["umount", "-l", str(point)], capture_output=True)


@pytest.fixture
def memory_limit():
    """``memory_limit(mib)``: this process may map at most ``mib`` MiB more than it has mapped now
    (RLIMIT_AS) until the test ends: a reader that tries to take more fails with MemoryError
    instead of taking the machine. Returns the limit in bytes."""
    import resource

    before = resource.getrlimit(resource.RLIMIT_AS)

    def limit(mib: int) -> int:
        with open("/proc/self/status") as f:
            mapped = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmSize:"))
        cap = mapped + mib * (1 << 20)
        resource.setrlimit(resource.RLIMIT_AS, (cap, before[1]))
        return cap

    yield limit
    resource.setrlimit(resource.RLIMIT_AS, before)
