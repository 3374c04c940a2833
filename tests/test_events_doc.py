"""docs/events.md is what the event models say, and every field of every event says what it is."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from pydantic import BaseModel

from gateway import events
from gateway.events import EventKind
from gateway.events_doc import FIX, kind_models, main, render

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "events.md"


def test_docs_events_md_is_generated_from_the_models() -> None:
    assert PAGE.read_text(encoding="utf-8") == render(), (
        f"docs/events.md is out of date with gateway/events.py: run `{FIX}` and commit it"
    )


def test_every_kind_has_its_model_and_section() -> None:
    models = kind_models()
    assert list(models) == list(EventKind)
    page = render()
    for kind, model in models.items():
        assert f"\n## {kind.value}\n" in page
        assert f"`gateway.events.{model.__name__}`" in page


def test_every_field_of_every_event_model_is_described() -> None:
    models = [
        m
        for m in vars(events).values()
        if isinstance(m, type) and issubclass(m, BaseModel) and m.__module__ == events.__name__
    ]
    undescribed = [
        f"{m.__name__}.{name}"
        for m in models
        for name, field in m.model_fields.items()
        if name != "kind" and not field.description
    ]
    assert undescribed == []


def test_check_names_the_fix_and_write_repairs(tmp_path: Path) -> None:
    stale = tmp_path / "events.md"
    stale.write_text("# Events\n\nold\n", encoding="utf-8")
    result = subprocess.run(
        [sys.executable, "-m", "gateway.events_doc", "--check", str(stale)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert result.returncode == 1
    assert FIX in result.stderr
    assert main(["--write", str(stale)]) == 0
    assert main(["--check", str(stale)]) == 0
    assert main(["--check", str(tmp_path / "missing.md")]) == 1


def test_docs_that_name_event_kinds_point_to_the_reference() -> None:
    for name in ("writing-a-sink.md", "durability.md", "architecture.md"):
        assert "events.md" in (ROOT / "docs" / name).read_text(encoding="utf-8"), name
