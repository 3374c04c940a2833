"""``settle_gc``: what ``fischer-gateway run`` and ``bench/ingest.py`` do to the collector."""

from __future__ import annotations

import gc
from collections.abc import Iterator

import pytest

from gateway.ops.gcsetup import GEN0_THRESHOLD, settle_gc


@pytest.fixture
def restored_gc() -> Iterator[None]:
    threshold, frozen = gc.get_threshold(), gc.get_freeze_count()
    yield
    gc.set_threshold(*threshold)
    if not frozen:
        gc.unfreeze()


@pytest.mark.usefixtures("restored_gc")
def test_it_freezes_start_up_once_and_raises_only_the_young_threshold() -> None:
    gc.unfreeze()
    _gen0, gen1, gen2 = gc.get_threshold()
    frozen, threshold = settle_gc()
    assert frozen == gc.get_freeze_count() > 0
    assert threshold == gc.get_threshold() == (GEN0_THRESHOLD, gen1, gen2)
    built_later = [[] for _ in range(100)]  # containers made once start-up is over
    assert settle_gc()[0] == frozen  # not frozen again: once per process
    assert built_later
    assert GEN0_THRESHOLD > 700  # above CPython's default, the point of it
