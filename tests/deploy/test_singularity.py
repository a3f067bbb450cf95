"""The Apptainer/Singularity definition, checked without Apptainer (it cannot be installed here):
spython parses it with its build arguments filled in the way ``apptainer build --build-arg``
fills them, and the image it describes is built and run with Docker."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

from tests.conftest import REPO
from tests.deploy.conftest import BASE_IMAGE, build_context

DEF = REPO / "singularity" / "swarmmap.def"


def arguments(text: str) -> dict[str, str]:
    """The ``%arguments`` section's defaults."""
    section = re.search(r"(?ms)^%arguments\n(.*?)(?=^%)", text).group(1)
    return dict(re.findall(r"^\s+(\w+)=(.*)$", section, re.M))


def render(text: str, **build_args: str) -> str:
    """The definition as Apptainer builds it: ``{{ NAME }}`` replaced, ``%arguments`` gone."""
    values = arguments(text) | build_args
    unknown = set(re.findall(r"\{\{\s*(\w+)\s*\}\}", text)) - values.keys()
    assert not unknown, f"placeholders without a default in %arguments: {unknown}"
    body = re.sub(r"\{\{\s*(\w+)\s*\}\}", lambda m: values[m.group(1)], text)
    return re.sub(r"(?ms)^%arguments\n.*?(?=^%)", "", body)


def recipe(tmp_path: Path, **build_args: str):
    from spython.main.parse.parsers import SingularityParser

    path = tmp_path / "swarmmap.def"
    path.write_text(render(DEF.read_text(), **build_args))
    return SingularityParser(str(path)).recipe["spython-base"]


def test_definition_parses_with_its_defaults_and_from_the_local_docker_engine(tmp_path):
    default = recipe(tmp_path)
    assert default.fromHeader == "python:3.11-slim"
    files = [line.split() for line in default.files]
    assert {dest for _, dest in files} >= {"/opt/swarmmap/shared", "/opt/swarmmap/services",
                                           "/usr/local/share/swarmmap/extra-ca.pem"}
    for src, _ in files:
        assert (REPO / src).exists(), f"%files names {src}, which the repository lacks"
    post = "\n".join(default.install)
    assert "--index-url" in post and "pip install --no-cache-dir /opt/swarmmap" in post
    local = recipe(tmp_path, BOOTSTRAP="docker-daemon", BASE_IMAGE=BASE_IMAGE, TORCH="cuda")
    assert local.fromHeader == BASE_IMAGE
    assert 'elif [ "cuda" = cuda ]' in "\n".join(local.install)
    assert re.search(r"(?m)^Bootstrap: docker-daemon$", render(DEF.read_text(), BOOTSTRAP="docker-daemon"))


def docker_equivalent(r) -> str:
    """A Dockerfile doing what the parsed definition does (%files, %post as one script, %runscript)."""
    lines = [f"FROM {r.fromHeader}"]
    lines += [f"COPY {line}" for line in r.files]
    lines += ["COPY post.sh /tmp/apptainer-post.sh", "RUN sh -e /tmp/apptainer-post.sh",
              "COPY runscript.sh /apptainer-runscript.sh", 'ENTRYPOINT ["sh", "/apptainer-runscript.sh"]']
    return "\n".join(lines) + "\n"


@pytest.mark.deploy
def test_definition_builds_from_the_local_docker_image_and_runs(docker_engine, tmp_path):
    r = recipe(tmp_path, BOOTSTRAP="docker-daemon", BASE_IMAGE=BASE_IMAGE)
    ctx = build_context(tmp_path / "ctx")
    (ctx / "post.sh").write_text("\n".join(r.install) + "\n")
    exports = "\n".join(f"export {line}" for line in r.environ)  # %environment, then %runscript
    (ctx / "runscript.sh").write_text(f"{exports}\n{r.cmd}\n")
    (ctx / "Dockerfile.sif").write_text(docker_equivalent(r))
    build = subprocess.run(["docker", "build", "-f", "Dockerfile.sif", "-t", "swarmmap-test/sif", "."], cwd=ctx,
                           capture_output=True, text=True, timeout=1500)
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    out = subprocess.run(["docker", "run", "--rm", "swarmmap-test/sif", "prepare", "--help"], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0 and "config.yaml" in out.stdout, out.stderr[-2000:]
