"""The README stays true: every config field, service and message kind is documented."""

from __future__ import annotations

from pydantic import BaseModel

from swarmmap.services.cli import DESCRIPTIONS
from swarmmap.shared.config import RunConfig
from swarmmap.shared.protocol import MESSAGE_TYPES
from tests.conftest import REPO

README = (REPO / "README.md").read_text()


def test_every_config_field_is_documented():
    missing = []
    for name, field in RunConfig.model_fields.items():
        if isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel):
            missing += [f"{name}.{sub}" for sub in field.annotation.model_fields if f"`{name}.{sub}`" not in README]
        elif f"`{name}`" not in README:
            missing.append(name)
    assert not missing, f"README lacks config fields: {missing}"


def test_every_command_and_message_is_documented():
    assert all(f"swarmmap {cmd}" in README for cmd in DESCRIPTIONS)
    assert all(f"`{kind}`" in README for kind in MESSAGE_TYPES)


def test_ci_runs_the_readme_test_command():
    assert "make test" in README and "make test" in (REPO / ".ci" / "run").read_text()
