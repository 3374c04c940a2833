"""docs/cot.md stays true to the code: its option tables are the config models' fields, and
every ``cot.md §N`` the code cites is a section of it."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from pydantic import BaseModel

from sinks.cot.sink import CotDestination, CotSinkConfig, CotStale, CotTls
from sinks.cot.source import CotSourceConfig

ROOT = Path(__file__).resolve().parents[3]
DOC = (ROOT / "docs" / "cot.md").read_text()


def _table_after(marker: str) -> list[str]:
    """The first column of the first table after ``marker``, without backticks or prefix."""
    rest = DOC[DOC.index(marker) :]
    rows = []
    for line in rest.splitlines()[1:]:
        if not line.startswith("|"):
            if rows:
                break
            continue
        rows.append(line.split("|")[1].strip().strip("`").rsplit(".", 1)[-1])
    return [row for row in rows[2:] if row]  # header and rule


@pytest.mark.parametrize(
    ("marker", "model"),
    [
        ("### The sink", CotSinkConfig),
        ("`stale` has one key per kind", CotStale),
        ("A destination written as a mapping", CotDestination),
        ("The `tls` mapping of a destination", CotTls),
        ("### The source", CotSourceConfig),
    ],
)
def test_each_options_table_lists_exactly_the_models_fields(
    marker: str, model: type[BaseModel]
) -> None:
    names = _table_after(marker)
    expected = set(model.model_fields) - ({"type"} if model is CotSourceConfig else set())
    assert sorted(names) == sorted(expected)


def test_every_section_the_code_cites_exists() -> None:
    sections = set(re.findall(r"^## (\d+)\. ", DOC, re.MULTILINE))
    cited = set()
    for path in [
        *ROOT.glob("sinks/**/*.py"),
        *ROOT.glob("gateway/**/*.py"),
        *ROOT.glob("gateway/data/*.yaml"),
    ]:
        cited |= set(re.findall(r"cot\.md`{0,2} (?:§|section )(\d+)", path.read_text()))
    assert cited
    assert cited <= sections
