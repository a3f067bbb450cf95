"""The README and docs/ stay true: every config field, command and message kind is documented,
the README stays a way in (short, with contents), and every link and image resolves."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest
from pydantic import BaseModel

from swarmmap.services.cli import build_parser, descriptions
from swarmmap.shared.run.config import RunConfig
from swarmmap.shared.wire.protocol import MESSAGE_TYPES
from tests.conftest import REPO

pytestmark = pytest.mark.timeout(60)

README = REPO / "README.md"
DOCS = REPO / "docs"
PAGES = [README, *sorted(DOCS.glob("*.md"))]
ALL_TEXT = "\n".join(p.read_text() for p in PAGES)
README_MAX_LINES = 400
# Wording about how the project was made, which a reader of the docs has no use for.
PROCESS_WORDS = ("the issue", "this stop", "earlier stop", "earlier session", "tried and reverted", "before this work",
                 "as measured before", "has not been run whole")

LINK = re.compile(r"(!?)\[([^\]]*)\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def prose(path: Path) -> str:
    """A page without its fenced code blocks (links there are examples, not links)."""
    return FENCE.sub("", path.read_text())


def anchor(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading anchor of a page (a repeated heading gets -1, -2, ... as on GitHub)."""
    seen: dict[str, int] = {}
    out = set()
    for line in prose(path).splitlines():
        m = re.match(r"^#{1,6} (.+)$", line)
        if not m:
            continue
        a = anchor(m.group(1))
        out.add(a if a not in seen else f"{a}-{seen[a]}")
        seen[a] = seen.get(a, 0) + 1
    return out


def links(path: Path) -> list[tuple[bool, str]]:
    """(is an image, target) of every Markdown link of a page outside code blocks."""
    return [(bang == "!", target) for bang, _, target in LINK.findall(prose(path))]


def test_every_config_field_is_in_the_reference():
    reference = (DOCS / "configuration.md").read_text()
    missing = []
    for name, field in RunConfig.model_fields.items():
        if isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel):
            missing += [f"{name}.{sub}" for sub in field.annotation.model_fields if f"`{name}.{sub}`" not in reference]
        elif f"`{name}`" not in reference:
            missing.append(name)
    assert not missing, f"docs/configuration.md lacks config fields: {missing}"


def test_every_command_and_message_is_documented():
    assert not [cmd for cmd in descriptions() if f"swarmmap {cmd}" not in ALL_TEXT], "undocumented commands"
    assert not [kind for kind in MESSAGE_TYPES if f"`{kind}`" not in ALL_TEXT], "undocumented message kinds"


def test_every_experiment_is_documented():
    experiment = _subcommands(build_parser())["experiment"]
    names = list(_subcommands(experiment))
    assert names, "swarmmap experiment has no subcommands"
    assert not [n for n in names if f"swarmmap experiment {n}" not in ALL_TEXT], "undocumented experiments"


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    actions = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(actions[0].choices) if actions else {}


def test_readme_is_a_way_in():
    text = README.read_text()
    assert len(text.splitlines()) <= README_MAX_LINES, f"README.md has {len(text.splitlines())} lines (at most {README_MAX_LINES})"
    headings = [h for h in re.findall(r"^## (.+)$", prose(README), re.M) if h != "Contents"]
    contents = text.split("## Contents", 1)[1].split("\n## ", 1)[0] if "## Contents" in text else ""
    assert contents, "README.md has no ## Contents"
    assert not [h for h in headings if f"](#{anchor(h)})" not in contents], "sections missing from the README's contents"


def test_readme_names_the_test_tiers_and_ci_runs_them():
    text = README.read_text()
    ci = (REPO / ".ci" / "run").read_text()
    for tier in ("make test", "make test-faults", "make test-deploy"):
        assert tier in text and tier in ci, tier


def test_every_link_and_image_resolves():
    broken = []
    for page in PAGES:
        for _, target in links(page):
            if re.match(r"^[a-z]+:", target):
                continue  # http(s), mailto: not checked offline
            file, _, frag = target.partition("#")
            dest = (page.parent / file).resolve() if file else page
            if not dest.exists():
                broken.append(f"{page.name}: {target} (no such file)")
            elif frag and dest.suffix == ".md" and frag not in anchors(dest):
                broken.append(f"{page.name}: {target} (no such heading)")
    assert not broken, broken


def test_every_figure_is_shown():
    shown = {(page.parent / target).resolve() for page in PAGES for image, target in links(page) if image}
    assert not [p.name for p in DOCS.glob("*.png") if p.resolve() not in shown], "docs/ PNGs no page shows"


def test_no_development_process_wording():
    found = [(p.name, w) for p in PAGES for w in PROCESS_WORDS if w in p.read_text().lower()]
    assert not found, found


def test_every_page_is_in_the_index():
    index = {target.partition("#")[0] for _, target in links(DOCS / "README.md")}
    assert not [p.name for p in DOCS.glob("*.md") if p.name != "README.md" and p.name not in index], "pages docs/README.md does not list"
