"""The deploy tier: real engines from the kit (../shared/kit), set up on demand.

These tests need root, the kit's scripts and Debian's packages (all there in CI); elsewhere
they skip and say why. ``make test-deploy`` runs them; ``make test`` does not."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO

KIT = REPO.parent / "shared" / "kit"
BASE_IMAGE = "local/python-torch:3.11"  # built by the kit's docker-base.sh
VENV_BIN = Path(sys.executable).parent


def run_kit(script: str) -> None:
    """Run one of the kit's idempotent set-up scripts; skip when this machine cannot."""
    path = KIT / script
    why = f"{path} is absent: no kit to set the engine up with" if not path.exists() else (
        f"{script} needs root" if os.geteuid() != 0 else None)
    if why and os.environ.get("CI") == "true":
        pytest.fail(f"the deploy tier cannot run in CI: {why}")  # a green CI must have run it
    if why:
        pytest.skip(why)
    proc = subprocess.run(["bash", str(path)], capture_output=True, text=True, timeout=1800)
    assert proc.returncode == 0, f"{script} failed:\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"


@pytest.fixture(scope="session")
def docker_engine() -> None:
    """A running Docker engine with the kit's base image."""
    run_kit("docker-base.sh")
    assert shutil.which("docker-compose") or shutil.which("docker"), "no compose after docker-base.sh"


@pytest.fixture(scope="session")
def slurm_cluster() -> None:
    """A one-node SLURM cluster (slurmctld, slurmd, munge)."""
    run_kit("slurm-local.sh")


def compose_command() -> list[str]:
    """``docker-compose`` (v1, here) or ``docker compose`` (v2)."""
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    return ["docker", "compose"]


def build_context(dest: Path, *extra: tuple[Path, str]) -> Path:
    """A copy of what the images are built from (the files the Dockerfile and .def name)."""
    dest.mkdir(parents=True)
    for name in ("pyproject.toml", "README.md", "shared", "services", "deploy", "singularity", ".dockerignore"):
        src = REPO / name
        (shutil.copytree if src.is_dir() else shutil.copy)(src, dest / name)
    for src, rel in extra:
        shutil.copy(src, dest / rel)
    return dest
