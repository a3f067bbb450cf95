"""The code keeps the shape its readers rely on: short functions, classes of one concept, the
learner's Algorithm 1 free of any transport, and registries that match the config."""

from __future__ import annotations

import ast
import subprocess
import sys
import typing

import pytest

from swarmmap.services.learner.consensus import RULES
from swarmmap.services.learner.registry import NODES
from swarmmap.shared.config import LearnerSettings
from swarmmap.shared.layout import EXTRA_VECTOR
from tests.conftest import REPO

LEARNER = REPO / "services" / "learner"


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


def test_algorithm1_imports_no_protocol_codec_bus_or_zenoh():
    """Not even through what it imports: the round machine sees vectors and rounds only."""
    code = ("import sys, swarmmap.services.learner.algorithm1, swarmmap.services.learner.clock\n"
            "print(' '.join(sorted(m for m in sys.modules if m.startswith(('swarmmap', 'zenoh')))))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    banned = {"zenoh", "swarmmap.shared.protocol", "swarmmap.shared.bus", "swarmmap.services.learner.codec",
              "swarmmap.shared.compression", "swarmmap.services.learner.zenoh_transport"}
    assert "swarmmap.services.learner.algorithm1" in loaded and not banned & set(loaded), loaded
    src = (LEARNER / "algorithm1.py").read_text()
    assert "def finish_round(self)" in src and "def on_state(self" in src and "def on_complete(self" in src


@pytest.mark.parametrize("field, registry", [("consensus", RULES), ("algorithm", NODES)])
def test_registries_name_exactly_what_the_config_allows(field, registry):
    allowed = set(typing.get_args(LearnerSettings.model_fields[field].annotation))
    assert set(registry) == allowed


def test_every_rule_whose_state_carries_more_is_known_to_the_layout():
    assert EXTRA_VECTOR["consensus"] <= set(RULES) and EXTRA_VECTOR["algorithm"] <= set(NODES)
