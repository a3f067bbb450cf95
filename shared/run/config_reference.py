"""The configuration reference (``docs/configuration.md``), generated from the config models.

    python -m swarmmap.shared.run.config_reference > docs/configuration.md

:func:`render` writes one Markdown table per section of :class:`RunConfig` (field, type or
choices with their bounds, default, description) and one of the presets, so the page says
exactly what the models accept; ``tests/shared/run/test_config_reference.py`` keeps the committed
page equal to it.
"""

from __future__ import annotations

import sys
import types
import typing
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel
from pydantic.fields import FieldInfo

from swarmmap.shared.run.config import DEFAULT_PRESET, ENV_PREFIX, PRESETS, RunConfig

INTRO = f"""# Configuration reference

<!-- Generated from the config models (shared/run/config.py); do not edit by hand:
     python -m swarmmap.shared.run.config_reference > docs/configuration.md -->

Every service of a run reads one configuration, `RunConfig`: a few top-level fields and one
section per service. `swarmmap up` writes the resolved whole as `RUN_DIR/config.yaml`, and every
service it starts reads that file. Values are taken with the precedence

    defaults < preset < config file (--config FILE.yaml) < environment ({ENV_PREFIX}...) < command line

- **Config file**: YAML shaped like a run's `config.yaml`: the top-level fields, then one mapping
  per section (`world:`, `learner:`, ...).
- **Environment**: `{ENV_PREFIX}<FIELD>` for a top-level field (`{ENV_PREFIX}ROBOTS=5`),
  `{ENV_PREFIX}<SECTION>__<FIELD>` for a section's (`{ENV_PREFIX}LEARNER__ROUNDS=50`,
  `{ENV_PREFIX}ZENOH__CONNECT='[tcp/10.0.0.2:7447]'`); lists and mappings are read as YAML,
  `null` unsets a field, and a misspelt `{ENV_PREFIX}*` name is refused with the closest one.
- **Command line**: every service takes the top-level fields and its own section's fields as
  `--field-name` (`swarmmap learner --rounds 50`), the Zenoh fields as `--zenoh-field-name`, and any
  field as `--set section.field=value` (repeatable, the value read as YAML:
  `--set learner.model_shape=[2,128,64,1]`).

A wrong value stops the service at start with exit status 2 and a message naming the field and
what it allows; unknown fields are refused too. "unset" below means the field has no value
unless one is given (`null` in YAML).
"""


def type_text(annotation: Any) -> str:
    """A field's type in words: ``int``, ``one of: a, b``, ``list of float``, ``path or unset``."""
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        inner = " or ".join(type_text(a) for a in args)
        return f"{inner} or unset" if len(args) < len(typing.get_args(annotation)) else inner
    if origin is Literal:
        return "one of: " + ", ".join(f"`{a}`" for a in typing.get_args(annotation))
    if origin is list:
        (item,) = typing.get_args(annotation)
        return f"list of {type_text(item)}"
    if annotation is Path:
        return "path"
    return getattr(annotation, "__name__", str(annotation))


def bounds_text(field: FieldInfo) -> str:
    """The field's bounds and pattern from its metadata: ``>= 1, <= 12``."""
    parts = []
    for item in field.metadata:
        for attr, op in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")):
            if getattr(item, attr, None) is not None:
                parts.append(f"{op} {getattr(item, attr)}")
        if getattr(item, "pattern", None):
            parts.append(f"matching `{item.pattern}`")
    return ", ".join(parts)


def value_text(value: Any) -> str:
    """A default as YAML would spell it: ``true``, ``[2, 256, 1]``, ``unset``."""
    if value is None:
        return "unset"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(value_text(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {value_text(v)}" for k, v in value.items()) + "}"
    return str(value)


def cell(text: str) -> str:
    """Text safe inside a Markdown table cell."""
    return text.replace("|", "\\|").replace("\n", " ")


def prose(text: str) -> str:
    """Plain text as Markdown prose: ``<i>`` would otherwise be read as an HTML tag."""
    return text.replace("<", "&lt;")


def field_row(name: str, field: FieldInfo) -> str:
    """One table row: field, type (with bounds), default, description."""
    kind = type_text(field.annotation)
    bounds = bounds_text(field)
    kind = f"{kind}, {bounds}" if bounds else kind
    default = value_text(field.get_default(call_default_factory=True))
    return f"| `{name}` | {cell(kind)} | `{cell(default)}` | {cell(prose(field.description or ''))} |"


def section_table(fields: dict[str, FieldInfo], prefix: str) -> list[str]:
    """The table of one section's fields, each named by its dotted path."""
    lines = ["| field | type | default | description |", "| --- | --- | --- | --- |"]
    return lines + [field_row(prefix + name, field) for name, field in fields.items()]


def is_section(field: FieldInfo) -> bool:
    """Whether a RunConfig field is a section (a nested model) rather than a value."""
    return isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel)


def preset_lines(name: str, tree: dict[str, Any]) -> list[str]:
    """A preset's settings: its top-level fields on one line, then one line per section."""
    top = [f"`{k}={value_text(v)}`" for k, v in tree.items() if not isinstance(v, dict)]
    lines = [f"### `{name}`", ""]
    lines += [f"- top level: {', '.join(top)}"] if top else []
    lines += [f"- `{k}`: " + ", ".join(f"`{f}={value_text(x)}`" for f, x in v.items()) for k, v in tree.items() if isinstance(v, dict)]
    return lines + [""]


def render() -> str:
    """The whole reference page as Markdown."""
    fields = RunConfig.model_fields
    top = {name: f for name, f in fields.items() if not is_section(f)}
    out = [INTRO, "## Top level", "", *section_table(top, ""), ""]
    for name, field in fields.items():
        if not is_section(field):
            continue
        model = field.annotation
        out += [f"## `{name}`", "", prose((model.__doc__ or "").strip().replace("``", "`")), ""]
        out += [*section_table(model.model_fields, f"{name}."), ""] if model.model_fields else ["No fields of its own.", ""]
    out += ["## Presets", "",
            "A preset (`--preset NAME`, the `preset` field) applies these settings over the defaults, under the config file, "
            "the environment and the command line; `swarmmap up` and `swarmmap prepare` apply "
            f"`{DEFAULT_PRESET}` when none is named.", ""]
    for name, tree in PRESETS.items():
        out += preset_lines(name, tree)
    return "\n".join(out)


if __name__ == "__main__":
    sys.stdout.write(render())
