"""The user documentation holds what it promises: every configuration key documented with its unit and its
default as the code has it, every page the README links to present, a README of user-guide length whose quick
start is the two commands that set everything up."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest
import yaml

from online_id.config import Settings, settings_from_dict

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
CONFIG_DOC = ROOT / "docs" / "config.md"
MAX_README_LINES = 350

# Pages other helpers' branches add; the README links to them before they are merged.
# Remove each entry once its page is on main (the test then requires the page).
AWAITING_MERGE: set[str] = set()

# The unit a key's name promises (units in names, conventions.md).
UNIT_OF_SUFFIX = {"_s": "s", "_hz": "Hz", "_rpm": "rpm", "_nm": "Nm", "_pct": "%"}


def config_keys(cls: type = Settings, prefix: str = "", default: object = None) -> dict[str, object]:
    """Every leaf key of the configuration dataclasses (``section.key``, ``mapping.role.key``) with its
    default value."""
    inst = default if default is not None else cls()
    keys: dict[str, object] = {}
    for f in dataclasses.fields(cls):
        value = getattr(inst, f.name)
        key = prefix + f.name
        if dataclasses.is_dataclass(value):
            keys.update(config_keys(type(value), key + ".", value))
        else:
            keys[key] = value
    return keys


def config_rows() -> dict[str, list[str]]:
    """The reference tables of docs/config.md: key -> [unit, default, range, meaning] (cells without the
    backquotes around the key and the default)."""
    rows: dict[str, list[str]] = {}
    for line in CONFIG_DOC.read_text(encoding="utf-8").splitlines():
        m = re.match(r"^\|\s*`([A-Za-z0-9_.]+)`\s*\|(.*)\|\s*$", line)
        if m:
            cells = [c.strip() for c in m.group(2).split("|")]
            assert m.group(1) not in rows, f"docs/config.md documents {m.group(1)} twice"
            rows[m.group(1)] = cells
    return rows


def as_yaml_value(value: object) -> object:
    """A dataclass default as YAML reads it back (tuples are lists)."""
    if isinstance(value, tuple):
        return [as_yaml_value(v) for v in value]
    return value


def test_the_key_walk_sees_every_section_and_the_nested_roles():
    keys = config_keys()
    sections = {k.split(".")[0] for k in keys}
    assert sections == {f.name for f in dataclasses.fields(Settings)}
    assert "mapping.dyno_torque.sign" in keys and keys["mapping.dyno_torque.sign"] == "braking"
    assert "dbc" in keys and len(keys) > 100


@pytest.mark.parametrize("key", sorted(config_keys()))
def test_every_config_key_is_documented_with_its_unit_and_its_default(key):
    rows = config_rows()
    assert key in rows, f"docs/config.md has no row for {key}"
    cells = rows[key]
    assert len(cells) == 4, f"docs/config.md row of {key}: expected unit, default, range, meaning; got {cells}"
    unit, default_cell, valid_range, meaning = cells
    assert unit, f"docs/config.md: {key} has no unit (write - for none)"
    name = key.rsplit(".", 1)[-1]
    for suffix, expected in UNIT_OF_SUFFIX.items():
        if name.endswith(suffix):
            assert unit == expected, f"docs/config.md: {key} is in {expected} by its name, documented as {unit!r}"
    assert valid_range and meaning, f"docs/config.md: {key} lacks its range or meaning"
    m = re.fullmatch(r"`([^`]*)`", default_cell)
    assert m, f"docs/config.md: the default of {key} should be one `value`, got {default_cell!r}"
    documented = yaml.safe_load(m.group(1))
    actual = as_yaml_value(config_keys()[key])
    assert documented == actual and type(documented) is type(actual) or (
        isinstance(actual, float) and isinstance(documented, (int, float)) and documented == actual
    ), f"docs/config.md: {key} defaults to {actual!r} in online_id/config.py, documented as {m.group(1)!r}"


def test_config_doc_documents_no_key_the_code_does_not_have():
    stale = sorted(set(config_rows()) - set(config_keys()))
    assert not stale, f"docs/config.md documents keys the configuration does not have: {stale}"


def readme_links() -> list[str]:
    """Relative link targets of the README (files of the repository), without their #anchors."""
    text = README.read_text(encoding="utf-8")
    targets = re.findall(r"\]\(([^)\s]+)\)", text)
    return sorted({t.split("#")[0] for t in targets if not re.match(r"^[a-z]+://|^#|^mailto:", t)} - {""})


def test_every_page_linked_from_the_readme_exists():
    links = readme_links()
    assert "docs/config.md" in links and "docs/detection.md" in links
    missing = [t for t in links if not (ROOT / t).exists() and t not in AWAITING_MERGE]
    assert not missing, f"README links to files that do not exist: {missing}"


def test_every_doc_page_is_reachable_from_the_readme():
    linked = set(readme_links())
    pages = {str(p.relative_to(ROOT)) for p in (ROOT / "docs").glob("*.md")}
    pages |= {"docs/history/README.md", "CHANGELOG.md"}
    assert not pages - linked, f"pages the README does not link to: {sorted(pages - linked)}"


def test_the_readme_is_a_user_guide_in_length():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md has {len(lines)} lines, at most {MAX_README_LINES}"


def test_the_quick_start_is_exactly_the_two_commands():
    text = README.read_text(encoding="utf-8")
    m = re.search(r"^## Quick start\n(.*?)(?=^## )", text, re.S | re.M)
    assert m, "README.md has no '## Quick start' section"
    blocks = re.findall(r"```(?:sh|bash|console)?\n(.*?)```", m.group(1), re.S)
    assert len(blocks) == 1, f"the quick start should hold one command block, has {len(blocks)}"
    commands = [line.split("#")[0].strip() for line in blocks[0].splitlines() if line.split("#")[0].strip()]
    assert commands == ["make demo", "make test"]
    makefile = (ROOT / "Makefile").read_text(encoding="utf-8")
    assert re.search(r"^demo:", makefile, re.M) and re.search(r"^test:", makefile, re.M)


@pytest.mark.parametrize("page", ["README.md", "docs/config.md"])
def test_the_configuration_examples_are_valid_configurations(page):
    """The YAML examples a bench copies from the README and the reference load as they are."""
    text = (ROOT / page).read_text(encoding="utf-8")
    blocks = re.findall(r"```yaml\n(.*?)```", text, re.S)
    assert blocks, f"{page} has no yaml example"
    for block in blocks:
        settings = settings_from_dict(yaml.safe_load(block), page)
        assert settings != Settings(), f"a yaml example of {page} sets nothing"
