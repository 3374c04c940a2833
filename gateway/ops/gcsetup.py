"""How the daemon sets up Python's cyclic garbage collector once start-up is done.

``fischer-gateway run`` and the benches that measure its pipeline (``bench/ingest.py``) call
``settle_gc`` after the gateway is built, so a bench measures what the daemon does:

- what start-up built (modules, schemas, the config, the gateway's objects) is frozen: a full
  collection would otherwise walk all of it, tens of milliseconds on the event loop, whenever
  one falls due while events flow. What is frozen and later dropped is still freed by its
  reference count;
- the youngest generation is collected every ``GEN0_THRESHOLD`` net container allocations
  instead of CPython's 700. Every event allocates a few short-lived containers (the event,
  its queue entries, the parsed message); at the default a young collection fell due every
  few hundred events and promoted whatever was alive at that instant to the older
  generations, whose collections are the costly ones. At 5,000 the time spent collecting
  fell by about 80 % in ``bench/ingest.py``'s pipeline; each young collection is longer
  (about 0.4 ms instead of 0.1 ms) and rarer. The older generations keep their default
  ratios. Figures: docs/operations.md, "The garbage collector".
"""

from __future__ import annotations

import gc

__all__ = ["GEN0_THRESHOLD", "settle_gc"]

#: Net container allocations between two collections of the youngest generation.
GEN0_THRESHOLD = 5000


def settle_gc() -> tuple[int, tuple[int, int, int]]:
    """Freeze what exists now (once per process) and raise the young generation's threshold.

    Returns the objects frozen and the thresholds now in force (the daemon logs them).
    """
    if gc.get_freeze_count() == 0:
        gc.collect()
        gc.freeze()
    _gen0, gen1, gen2 = gc.get_threshold()
    gc.set_threshold(GEN0_THRESHOLD, gen1, gen2)
    return gc.get_freeze_count(), (GEN0_THRESHOLD, gen1, gen2)
