"""The ``swarmmap`` command's help: real defaults, a version, examples, everyday flags first,
plain text (no RST markup), every command listed."""

from __future__ import annotations

import argparse
import re
import subprocess
from importlib import metadata

import pytest

from swarmmap.services.cli import build_parser, descriptions
from swarmmap.shared.run.config import DEFAULT_PRESET, resolve
from swarmmap.shared.run.flags import config_from_args
from tests.conftest import SWARMMAP, clean_env

pytestmark = pytest.mark.timeout(60)


def subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """Every (sub)command's parser by its name, ``experiment consensus`` included."""
    found = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                found[name] = sub
                found.update({f"{name} {k}": v for k, v in subparsers(sub).items()})
    return found


def help_of(*command: str) -> str:
    return subparsers(build_parser())[" ".join(command)].format_help()


@pytest.mark.integration
def test_version_comes_from_the_package_metadata():
    proc = subprocess.run([*SWARMMAP, "--version"], capture_output=True, text=True, timeout=30, env=clean_env())
    assert proc.returncode == 0 and proc.stdout.strip() == f"swarmmap {metadata.version('swarmmap')}"


def test_up_help_shows_what_a_plain_up_runs():
    plain = resolve(preset=DEFAULT_PRESET, environ={})
    text = " ".join(help_of("up").split())
    assert f"--robots ROBOTS number of robots (and lidar streamers and learners) [default: {plain.robots}]" in text
    assert f"[default: {plain.learner.rounds}]" in text and f"[default: {DEFAULT_PRESET}]" in text
    assert "[default: default]" not in text and "made from the time the run starts" in text
    assert plain.robots != resolve(environ={}).robots, "the check needs a preset that changes the robots"


def test_everyday_flags_come_first_and_zenoh_and_tls_are_advanced():
    text = help_of("up")
    options = text[text.index("everyday options"):]
    order = [options.index(f"\n  {flag} ") for flag in
             ("--preset", "--robots", "--rounds", "--model", "--floorplan", "--waypoints", "--run-dir", "--device", "--seed")]
    assert order == sorted(order)
    advanced = options.index("advanced: Zenoh transport and TLS")
    assert order[-1] < options.index("\n  --config ") < advanced
    for flag in ("--zenoh-connect", "--zenoh-secrets", "--insecure"):
        assert options.index(f"\n  {flag} ") > advanced


def test_device_on_up_sets_the_learners_device():
    args = build_parser().parse_args(["up", "--device", "cpu"])
    assert config_from_args(args, environ={}, preset=DEFAULT_PRESET).learner.device == "cpu"


def test_no_help_text_holds_rst_markup_and_every_command_is_listed():
    parser = build_parser()
    top = parser.format_help()
    for name in descriptions():
        assert re.search(rf"^    {name}\b", top, re.MULTILINE), f"{name} is not listed in swarmmap --help"
    assert "consensus" in top and "examples:" in top and "examples:" in help_of("up")
    for name, sub in subparsers(parser).items():
        assert "`" not in sub.format_help(), f"swarmmap {name} --help shows RST backticks"
    assert "`" not in top


def test_run_tools_take_their_paths():
    args = build_parser().parse_args(["logs", "runs/x", "learner-0", "--tail", "5"])
    assert (str(args.run_dir), args.service, args.tail) == ("runs/x", "learner-0", 5)
    assert str(build_parser().parse_args(["runs"]).folder) == "runs"
    assert build_parser().parse_args(["compare", "a", "b=B"]).runs == ["a", "b=B"]
    assert str(build_parser().parse_args(["status", "runs/x"]).run_dir) == "runs/x"
