"""Hypothesis strategies for ST 0601 values, shared by the KLV codec tests."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from hypothesis import strategies as st

from sinks.klv.st0601 import TAGS, Tag

#: Text as ST 0107 wants it: printable ASCII, not starting or ending with a blank.
ASCII = st.from_regex(r"\A[!-~]([ -~]{0,38}[!-~])?\Z")
TIMES = st.datetimes(
    # hypothesis takes naive bounds and adds the zone itself.
    min_value=datetime(1971, 1, 1),  # noqa: DTZ001
    max_value=datetime(2100, 1, 1),  # noqa: DTZ001
    timezones=st.just(UTC),
)


def value_strategy(t: Tag) -> st.SearchStrategy[Any]:
    """Values inside ``t``'s range, of the type ``encode`` takes."""
    if t.kind in ("umap", "smap", "imapb"):
        return st.floats(t.low, t.high, allow_nan=False)
    if t.kind == "text":
        return ASCII
    if t.kind == "time":
        return TIMES
    if t.kind == "bytes":
        return st.binary(max_size=40)
    bits = 8 * t.length
    if t.kind == "int":
        return st.integers(-(1 << (bits - 1)), (1 << (bits - 1)) - 1)
    return st.integers(0, (1 << bits) - 1)


def packets(tags: list[int] | None = None) -> st.SearchStrategy[dict[int, Any]]:
    """A ``{tag: value}`` over a random subset of ``tags`` (every interpreted tag but 1)."""
    chosen = [k for k in (tags or sorted(TAGS)) if k != 1]
    return st.fixed_dictionaries({}, optional={k: value_strategy(TAGS[k]) for k in chosen})
