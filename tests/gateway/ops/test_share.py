"""What ``files --out`` writes: links into the shipped set kept, others named in words."""

from __future__ import annotations

import pytest

from gateway.ops import share


def test_links_and_pictures_outside_the_share_are_named_not_followed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    text = (
        "See ![The live map](docs/map.png), [the map](docs/map.md#2-options), "
        "[the bench](bench/map_load.py) and [the web](https://example.org/x).\n"
    )
    monkeypatch.setattr(share, "read_shared", lambda name: text)
    assert share.shipped_text("README.md") == (
        "See The live map (picture: `docs/map.png` in the source tree), "
        "[the map](map.md#2-options), the bench (`bench/map_load.py` in the source tree) "
        "and [the web](https://example.org/x).\n"
    )
