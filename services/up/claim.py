"""Compose's start of a run: the run directory checked, its config written, its signer.

``python -m swarmmap.services.up.claim start`` is the first step of a compose run (the ``start``
container runs it, see deploy/docker/entrypoint.sh; it runs no service and joins no Zenoh
session): from the same environment as every service, it checks the run directory as ``swarmmap up`` does (a
finished run: refused; one that did not finish: resumed with ``SWARMMAP_UP__RESUME=true`` when its
settings are the same, refused otherwise), writes the run's ``config.yaml``, makes the run's CA (its key in
this process's memory only: :class:`~swarmmap.shared.wire.secrets.Signer`), forgets the claims of
the containers of an earlier ``up``, and leaves its verdict in ``START/start`` (``ok``, or why
not; START is ``SWARMMAP_START``, a folder the services mount read-only, else the claims folder),
which every other container of the run reads before it starts its service. Then it signs each
service's certificate (each container makes its own key and asks for the identity it claimed,
``zenoh.signer``) until the run is over: only the identities of the services compose.yaml runs
(mounted at COMPOSE_FILE), each for one key.
"""

from __future__ import annotations

import fcntl
import logging
import os
import sys
import threading
import time
from pathlib import Path

import yaml

from swarmmap.shared.run.atomic import atomic_write_text
from swarmmap.shared.run.config import ConfigError, RunConfig, resolve
from swarmmap.shared.run.runtime import setup_logging, shutdown_event
from swarmmap.shared.wire.claims import CLAIMS_ENV, forget_claims
from swarmmap.shared.wire.secrets import Signer, router_names
from swarmmap.shared.wire.services import identities, kinds

START_ENV = "SWARMMAP_START"  # the folder of the start's verdict and the services' lock (compose: read-only to them)
COMPOSE_FILE = Path("/etc/swarmmap/compose.yaml")  # where compose.yaml mounts itself into the start container
SIGNER_LINGER_S = 10.0  # past the recorder's linger: by then it has left, and compose's `up` ends with the signer at the latest

log = logging.getLogger("claim")


def start(environ: dict[str, str] | None = None, serve: bool = False, stop: threading.Event | None = None,
          compose_file: Path = COMPOSE_FILE) -> int:
    """Compose's first step of a run (see the module's docstring); returns the exit status and
    leaves its verdict in ``START/start``: ``ok``, or why the run did not start. With
    ``zenoh.signer`` set, the run's signer is made before the verdict (so that no service sees
    an earlier run's CA) and, with ``serve``, signs the services' requests until the run is over
    (those of the services ``compose_file`` runs, :func:`compose_identities`)."""
    environ = os.environ if environ is None else environ
    folder = Path(environ[CLAIMS_ENV]) if environ.get(CLAIMS_ENV) else None
    verdicts = Path(environ[START_ENV]) if environ.get(START_ENV) else folder
    signer = None
    try:
        cfg = begin(environ)
        if cfg.zenoh.signer is not None and not cfg.zenoh.insecure:
            names = compose_identities(cfg.robots, compose_file)
            signer = Signer(cfg.zenoh.signer, cfg.run_id, names, router_names(cfg.zenoh.connect, cfg.router.hosts),
                            cfg.zenoh.signer_requests)
            log.info("signer of run %s in %s: its CA key is held in this process's memory only; it signs %s, each once",
                     cfg.run_id, cfg.zenoh.signer, ", ".join(names))
        if folder is not None:
            forget_claims(folder)
        if verdicts is not None:
            verdicts.mkdir(parents=True, exist_ok=True)
            (verdicts / "running").touch()  # the services' lock (they may not make it: the folder is read-only to them)
        verdict = "ok"
    except ConfigError as exc:
        print(exc.message, file=sys.stderr)
        verdict = exc.message
    except OSError as exc:  # a run directory or a claims folder it may not write
        hint = " (claims of another user: `docker compose down --volumes` clears them)" if folder and str(folder) in str(exc) else ""
        verdict = f"the run cannot start: {exc}{hint}"
        print(verdict, file=sys.stderr)
    if verdicts is not None:
        atomic_write_text(verdicts / "start", verdict + "\n")
    if verdict != "ok":
        return 2
    if serve and signer is not None:
        sign_until_over(signer, cfg, stop or threading.Event(), verdicts / "running" if verdicts is not None else None)
    return 0


def compose_identities(robots: int, compose_file: Path) -> list[str]:
    """The identities the signer signs: those of the services compose_file's ``services:`` runs
    (each kind of service it names: one, or one per robot), never a tool's (``up``, ``status``) or
    a kind it does not run; without the file, those of the services ``swarmmap up`` starts."""
    every = kinds()
    services = {name for name, kind in every.items() if kind.runner is not None}  # not up's, status's
    try:
        named = set((yaml.safe_load(compose_file.read_text()) or {}).get("services") or {})
    except (OSError, yaml.YAMLError, AttributeError):
        named = {name for name in services if every[name].up_order is not None}
    return [name for name in identities(robots) if name.rsplit("-", 1)[0] in named & services]


def sign_until_over(signer: Signer, cfg: RunConfig, stop: threading.Event, running: Path | None = None) -> None:
    """Sign the services' requests until the run is over: its summary written (the recorder
    writes it last) and every service gone (none holds its shared lock on ``running``, see
    deploy/docker/entrypoint.sh), at most the recorder's linger time after; or until stopped."""
    summary, began = cfg.run_dir / "summary.json", time.time()
    over_at = None
    while not stop.is_set():
        signer.serve_once()
        if over_at is None and summary.exists() and summary.stat().st_mtime >= began:
            over_at = time.monotonic()
            log.info("the run is over (%s); no more certificates once its services have left", summary)
        if over_at is not None and (nobody_running(running) or time.monotonic() - over_at > cfg.recorder.linger_s + SIGNER_LINGER_S):
            return
        stop.wait(0.2)


def nobody_running(running: Path | None) -> bool:
    """Whether no service holds its shared lock on ``running`` (False when there is no such file)."""
    if running is None or not running.exists():
        return False
    with open(running, "a") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False
        fcntl.flock(f, fcntl.LOCK_UN)
        return True


def begin(environ: dict[str, str]) -> RunConfig:
    """The checks and writes of the start of a run; returns its config, or raises ConfigError
    naming what is wrong."""
    from swarmmap.services.up.launcher import WayOut, prepare, run_dir_problem, write_config
    from swarmmap.shared.world.floorplan import PlanError
    from swarmmap.shared.world.recording import RecordingError

    cfg = resolve(environ=environ)
    setup_logging(cfg.log_level, "start")
    if cfg.run_dir is None:
        raise ConfigError("config error:\n  run_dir: the start of a run needs its run directory (SWARMMAP_RUN_DIR)")
    try:
        cfg = prepare(cfg)
    except (RecordingError, PlanError) as exc:
        raise ConfigError(str(exc)) from None
    ways = WayOut(other="choose another SWARMMAP_RUN_ID", resume="SWARMMAP_UP__RESUME=true")
    if (why := run_dir_problem(cfg, ways)) is not None:
        raise ConfigError(f"config error:\n  run_dir: {why}")
    log.info("run %s: %d robots, config %s", cfg.run_id, cfg.robots, write_config(cfg))
    return cfg


def main(argv: list[str] | None = None) -> int:
    """``python -m swarmmap.services.up.claim start``: the start of a compose run, then its signer."""
    argv = sys.argv[1:] if argv is None else argv
    if argv != ["start"]:
        print("usage: python -m swarmmap.services.up.claim start", file=sys.stderr)
        return 2
    return start(serve=True, stop=shutdown_event())


if __name__ == "__main__":
    sys.exit(main())
