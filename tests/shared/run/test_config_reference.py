"""The configuration reference in docs/ stays equal to the config models it is generated from."""

from __future__ import annotations

import pytest

from swarmmap.shared.run.config import PRESETS, RunConfig
from swarmmap.shared.run.config_reference import render, type_text, value_text
from tests.conftest import REPO

pytestmark = pytest.mark.timeout(30)

REGENERATE = "python -m swarmmap.shared.run.config_reference > docs/configuration.md"


def test_committed_reference_equals_the_models():
    committed = (REPO / "docs" / "configuration.md").read_text()
    assert committed == render(), f"docs/configuration.md is out of date with shared/run/config.py: run `{REGENERATE}`"


def test_every_field_has_a_row_with_its_default():
    page = render().splitlines()
    for name, field in RunConfig.model_fields.items():
        model = field.annotation
        if isinstance(model, type) and hasattr(model, "model_fields"):
            rows = {f"{name}.{sub}": f for sub, f in model.model_fields.items()}
        else:
            rows = {name: field}
        for path, info in rows.items():
            row = [line for line in page if line.startswith(f"| `{path}` |")]
            assert len(row) == 1, f"{path}: {len(row)} rows"
            assert f"| `{value_text(info.get_default(call_default_factory=True))}` |" in row[0], row[0]


def test_choices_and_bounds_are_spelled_out():
    page = render()
    assert "| `learner.optimizer` | one of: `adam`, `adamw`, `sgd` | `adam` |" in page
    assert "| `robots` | int, >= 1, <= 64 | `3` |" in page
    assert "| `learner.compute_slots` | int or unset, >= 0 | `unset` |" in page
    assert type_text(list[int]) == "list of int"


def test_every_preset_is_listed_with_its_settings():
    page = render()
    for name in PRESETS:
        assert f"### `{name}`" in page
    assert "`rounds=60`" in page.split("### `smoke`")[1].split("###")[0]


def test_html_like_text_is_escaped():
    # robot-<i>.pt would render as robot-.pt in italics
    assert "robot-&lt;i>.pt" in render()
