"""The event reference (docs/events.md), generated from the models in ``gateway.events``.

``python -m gateway.events_doc`` prints the page; ``--write docs/events.md`` writes it and
``--check docs/events.md`` exits 1 when the file differs from what the models say. Each kind's
meaning is its model's docstring; each field's row gives its type in words, whether it is
required or its default, its constraints (``ge``, ``le``, ``pattern``, lengths) and its
``Field(description=...)``.
"""

from __future__ import annotations

import argparse
import enum
import inspect
import json
import sys
import types
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, Literal, Union, get_args, get_origin

import annotated_types as at
from pydantic import AwareDatetime, BaseModel, JsonValue
from pydantic.fields import FieldInfo

from gateway import events
from gateway.events import DURABLE_KINDS, Event, EventKind

__all__ = ["kind_models", "main", "render"]

FIX = "python -m gateway.events_doc --write docs/events.md"


def kind_models() -> dict[EventKind, type[BaseModel]]:
    """Each kind and its model, in ``EventKind`` order (read from the ``Event`` union)."""
    union = get_args(get_args(Event)[0])
    found: dict[EventKind, type[BaseModel]] = {}
    for model in union:
        default = model.model_fields["kind"].default
        found[EventKind(default)] = model
    return {kind: found[kind] for kind in EventKind}


def _doc(obj: object) -> str:
    return _markdown(inspect.cleandoc(obj.__doc__ or ""))


def _markdown(text: str) -> str:
    """reStructuredText's ``code`` as Markdown's `code`."""
    return text.replace("``", "`")


def _anchor(name: str) -> str:
    """The anchor Markdown renderers give a heading of one word (underscores kept)."""
    return name.lower()


class _Names:
    """The nested models and enums the fields refer to, collected as they are written."""

    def __init__(self) -> None:
        self.models: dict[str, type[BaseModel]] = {}
        self.enums: dict[str, type[enum.Enum]] = {}

    def type_of(self, annotation: Any) -> str:
        """``annotation`` in words, nested types as links to their own section."""
        origin = get_origin(annotation)
        args = get_args(annotation)
        if origin is Annotated:
            inner, *meta = args
            limits = [c for m in meta if isinstance(m, FieldInfo) for c in _constraints(m)]
            shown = self.type_of(inner)
            return f"{shown} ({', '.join(limits)})" if limits else shown
        if origin in (Union, types.UnionType):
            kept = [a for a in args if a is not type(None)]
            shown = " or ".join(self.type_of(a) for a in kept)
            return f"{shown} or null" if len(kept) < len(args) else shown
        if origin is Literal:
            shown = ", ".join(f"`{_value(a)}`" for a in args)
            return f"always {shown}" if len(args) == 1 else f"one of {shown}"
        if origin is tuple:
            return f"list of {self.type_of(args[0])}"
        if origin is dict and args and args[1] == JsonValue:
            return "JSON object"
        if annotation is AwareDatetime:
            return "time (ISO 8601, with zone)"
        if isinstance(annotation, type) and issubclass(annotation, enum.Enum):
            self.enums[annotation.__name__] = annotation
            return f"[{annotation.__name__}](#{_anchor(annotation.__name__)})"
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            if "kind" in annotation.model_fields:  # an event inside an event (Handoff.track)
                kind = _value(annotation.model_fields["kind"].default)
                return f"[{annotation.__name__}](#{_anchor(kind)}) event"
            if annotation.__name__ not in self.models:
                self.models[annotation.__name__] = annotation
                for field in annotation.model_fields.values():
                    self.type_of(field.annotation)
            return f"[{annotation.__name__}](#{_anchor(annotation.__name__)})"
        words = {str: "string", int: "integer", float: "number", bool: "boolean"}
        return words.get(annotation, getattr(annotation, "__name__", str(annotation)))


def _value(value: object) -> str:
    """A literal as it reads in JSON (``true``, ``hostile``)."""
    if isinstance(value, enum.Enum):
        value = value.value
    return value if isinstance(value, str) else json.dumps(value)


def _number(value: object) -> str:
    if isinstance(value, float) and value.is_integer() and abs(value) >= 1e6:
        return f"{value:.0e}".replace("e+0", "e").replace("e+", "e")
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    if isinstance(value, int) and value >= 2**20:
        exponent = value.bit_length() - 1
        if value == 2**exponent:
            return f"2^{exponent}"
    return str(value)


def _constraints(field: FieldInfo) -> list[str]:
    shown = []
    for item in field.metadata:
        if isinstance(item, at.Ge):
            shown.append(f"≥ {_number(item.ge)}")
        elif isinstance(item, at.Gt):
            shown.append(f"> {_number(item.gt)}")
        elif isinstance(item, at.Le):
            shown.append(f"≤ {_number(item.le)}")
        elif isinstance(item, at.Lt):
            shown.append(f"< {_number(item.lt)}")
        elif isinstance(item, at.MinLen):
            shown.append(f"length ≥ {item.min_length}")
        elif isinstance(item, at.MaxLen):
            shown.append(f"length ≤ {item.max_length}")
        elif getattr(item, "pattern", None) is not None:
            shown.append(f"pattern `{item.pattern}`")
    return shown


def _default(field: FieldInfo) -> str:
    if field.is_required():
        return "required"
    if field.default_factory is not None:
        value: Any = field.default_factory()  # type: ignore[call-arg]
    else:
        value = field.default
    if isinstance(value, enum.Enum):
        value = value.value
    if isinstance(value, tuple | frozenset):
        value = list(value)
    return f"`{json.dumps(value)}`"


def _cell(text: str) -> str:
    return " ".join(text.split()).replace("|", "\\|")


def _fields(model: type[BaseModel], names: _Names) -> list[str]:
    rows = [
        "| Field | Type | Default | Constraints | Description |",
        "| --- | --- | --- | --- | --- |",
    ]
    for name, field in model.model_fields.items():
        if name == "kind":
            kind = _value(field.default)
            rows.append(
                f"| `kind` | string | `{json.dumps(kind)}` | always `{kind}` "
                "| The discriminator: what routes and `kinds` name. |"
            )
            continue
        cells = (
            f"`{name}`",
            names.type_of(field.annotation),
            _default(field),
            ", ".join(_constraints(field)) or "",
            _markdown(field.description or ""),
        )
        rows.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    return rows


def _extension_limits() -> list[str]:
    return [
        "Limits of an `extension` event, checked when it is made: `type` matches "
        f"`{events.EXTENSION_TYPE_PATTERN}` and is at most {events.EXTENSION_TYPE_MAX} "
        f"characters; `data` is a JSON object of at most {events.EXTENSION_DATA_MAX_BYTES} "
        f"bytes as compact JSON, nested at most {events.EXTENSION_DATA_MAX_DEPTH} levels "
        "deep. A processor declares the types it publishes and the model of each one's "
        "`data` ([writing-a-sink.md](writing-a-sink.md#publishing-your-own-event-types)).",
        "",
    ]


def render() -> str:
    """The whole page, as docs/events.md holds it."""
    names = _Names()
    models = kind_models()
    out = [
        "# Events",
        "",
        "<!-- Generated from gateway/events.py; do not edit. Regenerate with",
        f"     {FIX} -->",
        "",
        "Every event kind the gateway publishes, and every field of each, from the models in "
        "`gateway/events.py`. A sink or processor declares the kinds it takes by these names "
        "(`kinds`), and so do routes.",
        "",
        _doc(events),
        "",
        "| Kind | Model | Delivery | Meaning |",
        "| --- | --- | --- | --- |",
    ]
    for kind, model in models.items():
        delivery = "durable" if kind in DURABLE_KINDS else "latest wins"
        first = _doc(model).split("\n\n")[0]
        out.append(
            f"| [`{kind.value}`](#{_anchor(kind.value)}) | `{model.__name__}` | {delivery} "
            f"| {_cell(first)} |"
        )
    out.append("")
    for kind, model in models.items():
        delivery = "durable" if kind in DURABLE_KINDS else "latest wins"
        out += [
            f"## {kind.value}",
            "",
            f"`gateway.events.{model.__name__}`, {delivery}.",
            "",
            _doc(model),
            "",
            *_fields(model, names),
            "",
        ]
        if kind is EventKind.EXTENSION:
            out += _extension_limits()
    out += ["## Types inside events", ""]
    done: set[str] = set()
    while len(done) < len(names.models):
        for name, model in sorted(names.models.items()):
            if name in done:
                continue
            done.add(name)
            out += [f"### {name}", "", _doc(model), "", *_fields(model, names), ""]
    for name, kind_enum in sorted(names.enums.items()):
        values = ", ".join(f"`{member.value}`" for member in kind_enum)
        out += [f"### {name}", "", _doc(kind_enum), "", f"Values: {values}.", ""]
    return "\n".join(out).rstrip("\n") + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """Print, write or check the page; exit 1 when ``--check`` finds it stale."""
    parser = argparse.ArgumentParser(prog="python -m gateway.events_doc", description=__doc__)
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--write", type=Path, metavar="PATH", help="write the page to PATH")
    group.add_argument("--check", type=Path, metavar="PATH", help="exit 1 if PATH differs")
    args = parser.parse_args(argv)
    page = render()
    if args.write is not None:
        args.write.write_text(page, encoding="utf-8")
        return 0
    if args.check is not None:
        try:
            current = args.check.read_text(encoding="utf-8")
        except OSError as exc:
            sys.stderr.write(f"{args.check}: {exc.strerror}; run {FIX}\n")
            return 1
        if current != page:
            sys.stderr.write(f"{args.check} is out of date with gateway/events.py; run {FIX}\n")
            return 1
        return 0
    sys.stdout.write(page)
    return 0


if __name__ == "__main__":
    sys.exit(main())
