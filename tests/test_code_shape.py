"""The code keeps the shape its readers rely on: short functions, classes of one concept, the
learner's Algorithm 1 free of any transport, and registries that match the config."""

from __future__ import annotations

import ast
import subprocess
import sys
import typing

import pytest

from swarmmap.services.learner.registry import NODES
from swarmmap.shared import plugins
from swarmmap.shared.learning.layout import EXTRA_VECTOR_ALGORITHMS
from swarmmap.shared.run.config import LearnerSettings
from tests.conftest import REPO

LEARNER = REPO / "services" / "learner"


@pytest.mark.integration
def test_no_function_in_services_or_shared_is_more_complex_than_15():
    proc = subprocess.run([sys.executable, "-m", "ruff", "check", "--select", "C901", "--config",
                           "lint.mccabe.max-complexity=15", "services", "shared"], cwd=REPO, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-1000:]


def spans(kind):
    for path in sorted(LEARNER.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, kind):
                yield f"{path.relative_to(REPO)}:{node.lineno} {node.name}", node.end_lineno - node.lineno + 1


def test_learner_classes_are_at_most_150_lines_and_functions_60():
    assert not [(where, n) for where, n in spans(ast.ClassDef) if n > 150]
    assert not [(where, n) for where, n in spans((ast.FunctionDef, ast.AsyncFunctionDef)) if n > 60]


@pytest.mark.integration
def test_algorithm1_imports_no_protocol_codec_bus_or_zenoh():
    """Not even through what it imports: the round machine sees vectors and rounds only."""
    code = ("import sys, swarmmap.services.learner.algorithm1, swarmmap.services.learner.clock\n"
            "print(' '.join(sorted(m for m in sys.modules if m.startswith(('swarmmap', 'zenoh')))))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    banned = {"zenoh", "swarmmap.shared.wire.protocol", "swarmmap.shared.wire.bus", "swarmmap.services.learner.codec",
              "swarmmap.shared.wire.compression", "swarmmap.services.learner.zenoh_transport"}
    assert "swarmmap.services.learner.algorithm1" in loaded and not banned & set(loaded), loaded
    src = (LEARNER / "algorithm1.py").read_text()
    assert "def finish_round(self)" in src and "def on_state(self" in src and "def on_complete(self" in src


def test_the_learning_rules_registry_names_exactly_what_the_config_allows():
    assert set(NODES) == set(typing.get_args(LearnerSettings.model_fields["algorithm"].annotation))


def test_every_consensus_module_is_a_registered_plugin_and_says_what_its_state_carries():
    builtin = {p.name: plugins.load("consensus", p.name) for p in plugins.installed("consensus") if p.builtin}
    modules = {path.stem for path in (LEARNER / "consensus").glob("*.py")} - {"__init__", "base", "builtin"}
    assert set(builtin) == modules == {"dinno", "ramen", "sigma", "dgvi"}
    assert [name for name, rule in builtin.items() if rule.extra_vector] == ["ramen"]
    assert EXTRA_VECTOR_ALGORITHMS <= set(NODES)
