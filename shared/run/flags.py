"""The command line of every swarmmap command that takes a config: a flag per config field (made
from the models, with their help and defaults), the common flags, and a config from parsed arguments."""

from __future__ import annotations

import argparse
import types
import typing
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel

from swarmmap.shared.run.config import PRESETS, RunConfig, ZenohSettings, _is_model, _set_path, apply_override, resolve

# ----------------------------------------------------------------------------- command line


def _base_type(annotation: Any) -> Any:
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        return _base_type(args[0]) if len(args) == 1 else annotation
    return annotation


def field_info(path: str) -> tuple[type[BaseModel], str]:
    """(the model that holds it, the field name) of a dotted config path, ``learner.rounds`` or ``robots``."""
    *section, name = path.split(".")
    model: type[BaseModel] = RunConfig.model_fields[section[0]].annotation if section else RunConfig
    if name not in model.model_fields:
        raise KeyError(path)
    return model, name


def default_text(value: Any) -> str:
    """`` [default: 7]`` for help texts; "" when there is nothing to show (None, an empty list)."""
    if value is None or value == [] or value == "":
        return ""
    if isinstance(value, list):
        value = ",".join(map(str, value)) if all(isinstance(v, int) for v in value) else " ".join(map(str, value))
    return f" [default: {value}]".replace("%", "%%")


def add_field_argument(group: argparse._ActionsContainer, path: str, flag: str | None = None, *,
                       defaults: RunConfig | None = None, help: str | None = None, shown_default: str | None = None) -> None:
    """Add the ``--flag`` of the config field at ``path`` (e.g. ``learner.rounds`` as ``--rounds``):
    its description, the default a plain run uses (from ``defaults``, e.g. the default preset's
    resolved config), and a metavar listing a choice's values; values are validated by pydantic."""
    model, name = field_info(path)
    field = model.model_fields[name]
    head = path.split(".")[0] if "." in path else "top"
    flag = flag or "--" + name.replace("_", "-")
    base = _base_type(field.annotation)
    if defaults is not None:
        default = getattr(getattr(defaults, head) if head != "top" else defaults, name)
    else:
        default = field.get_default(call_default_factory=True)
    shown = f" [default: {shown_default}]" if shown_default else default_text(default)
    text = (help or field.description or "").replace("%", "%%") + shown
    kwargs: dict[str, Any] = {"dest": f"{head}.{name}", "default": argparse.SUPPRESS, "help": text, "metavar": name.upper()}
    if base is bool:
        kwargs["action"] = argparse.BooleanOptionalAction
        del kwargs["metavar"]
    elif typing.get_origin(base) is list:
        kwargs["nargs"] = "+"
    elif typing.get_origin(base) is Literal:
        kwargs["metavar"] = "{" + ",".join(map(str, typing.get_args(base))) + "}"
    group.add_argument(flag, **kwargs)


def add_model_arguments(parser: argparse._ActionsContainer, model: type[BaseModel], section: str | None,
                        flag_prefix: str = "", skip: typing.Iterable[str] = (), defaults: RunConfig | None = None,
                        shown: dict[str, str] | None = None) -> None:
    """Add one ``--flag`` per field of ``model`` (the RunConfig's top level when ``section`` is None)."""
    for name, field in model.model_fields.items():
        if name in skip or _is_model(field.annotation):
            continue
        path = f"{section}.{name}" if section else name
        add_field_argument(parser, path, "--" + flag_prefix + name.replace("_", "-"), defaults=defaults,
                           shown_default=(shown or {}).get(path))


ADVANCED_TITLE = "advanced: Zenoh transport and TLS"


def add_common_arguments(parser: argparse.ArgumentParser, section: str | None, *, defaults: RunConfig | None = None,
                         skip: typing.Iterable[str] = (), shown: dict[str, str] | None = None,
                         more: typing.Iterable[tuple[str, str, str | None]] = ()) -> argparse._ArgumentGroup:
    """The options every service takes: config file, preset, run, ``--set``, its section, and
    Zenoh (in an advanced group); ``skip`` names top-level fields already added (everyday flags),
    ``more`` other fields for the run group as (path, flag, help or None). Returns the advanced
    group, for a command's own transport flags."""
    skip = set(skip)
    g = parser.add_argument_group("run")
    g.add_argument("--config", type=Path, default=None, help="YAML config file, e.g. a run's config.yaml (under the "
                                                             "environment and the command line)")
    if "preset" not in skip:
        g.add_argument("--preset", dest="top.preset", default=argparse.SUPPRESS, metavar="{" + ",".join(PRESETS) + "}",
                       help="named preset applied under the config file")
    add_model_arguments(g, RunConfig, None, skip={"preset", *skip}, defaults=defaults, shown=shown)
    for path, flag, text in more:
        add_field_argument(g, path, flag, defaults=defaults, help=text)
    g.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override any field by its dotted path, e.g. --set learner.lr_start=0.01 or "
                        "--set learner.model_shape=[2,64,32,1] (repeatable)")
    if section is not None:
        s = parser.add_argument_group(section)
        add_model_arguments(s, RunConfig.model_fields[section].annotation, section, defaults=defaults, shown=shown)
    z = parser.add_argument_group(ADVANCED_TITLE)
    add_model_arguments(z, ZenohSettings, "zenoh", flag_prefix="zenoh-", defaults=defaults)
    return z


def config_from_args(args: argparse.Namespace, environ: dict[str, str] | None = None,
                     preset: str | None = None) -> RunConfig:
    """Turn parsed arguments into the resolved RunConfig (see :func:`resolve`)."""
    cli: dict[str, Any] = {}
    for dest, value in vars(args).items():
        if "." not in dest:
            continue
        head, field = dest.split(".", 1)
        _set_path(cli, [field] if head == "top" else [head, field], value)
    for item in getattr(args, "overrides", []):
        apply_override(cli, item)
    return resolve(cli, config_file=getattr(args, "config", None), preset=preset, environ=environ)
