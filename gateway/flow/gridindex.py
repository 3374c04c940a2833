"""A spatial hash grid over plane coordinates in metres: which keys lie within a radius.

``GridIndex`` files each key under the square cell its position falls in (cell size
configurable), so ``within`` looks only at the cells a query circle overlaps, never at every
key. It is exact: ``within`` returns precisely the keys whose stored position is at most
``radius_m`` from the query point, as a brute-force scan would. When a query circle covers
more cells than there are occupied cells, the occupied cells are walked instead, so a huge
radius costs no more than a scan.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Iterator
from typing import Generic, TypeVar

__all__ = ["GridIndex"]

K = TypeVar("K", bound=Hashable)
Cell = tuple[int, int]


class GridIndex(Generic[K]):
    """Keys by position on a plane (metres), bucketed in square cells of ``cell_m``."""

    def __init__(self, cell_m: float) -> None:
        if not cell_m > 0 or math.isinf(cell_m):
            raise ValueError(f"cell_m must be a positive finite number, found {cell_m!r}")
        self.cell_m = cell_m
        self._cells: dict[Cell, set[K]] = {}
        self._where: dict[K, tuple[float, float, Cell]] = {}

    def __len__(self) -> int:
        return len(self._where)

    def __contains__(self, key: object) -> bool:
        return key in self._where

    def __iter__(self) -> Iterator[K]:
        return iter(self._where)

    def _cell(self, x_m: float, y_m: float) -> Cell:
        return math.floor(x_m / self.cell_m), math.floor(y_m / self.cell_m)

    def insert(self, key: K, x_m: float, y_m: float) -> None:
        """File ``key`` at (x, y); ``KeyError`` if it is already filed (use ``move``)."""
        if key in self._where:
            raise KeyError(f"{key!r} is already in the index")
        cell = self._cell(x_m, y_m)
        self._cells.setdefault(cell, set()).add(key)
        self._where[key] = (x_m, y_m, cell)

    def move(self, key: K, x_m: float, y_m: float) -> None:
        """Re-file ``key`` at (x, y); ``KeyError`` if it is not filed."""
        _, _, old = self._where[key]
        cell = self._cell(x_m, y_m)
        if cell != old:
            self._unfile(key, old)
            self._cells.setdefault(cell, set()).add(key)
        self._where[key] = (x_m, y_m, cell)

    def remove(self, key: K) -> None:
        """Forget ``key``; ``KeyError`` if it is not filed."""
        _, _, cell = self._where.pop(key)
        self._unfile(key, cell)

    def _unfile(self, key: K, cell: Cell) -> None:
        bucket = self._cells[cell]
        bucket.discard(key)
        if not bucket:
            del self._cells[cell]

    def position(self, key: K) -> tuple[float, float]:
        """Where ``key`` is filed; ``KeyError`` if it is not."""
        x_m, y_m, _ = self._where[key]
        return x_m, y_m

    def within(self, x_m: float, y_m: float, radius_m: float) -> list[K]:
        """The keys filed at most ``radius_m`` from (x, y), in no particular order."""
        if radius_m < 0:
            return []
        # x - r can round past a key exactly r away into the next cell: widen by a few ulps.
        reach = radius_m + 4 * math.ulp(abs(x_m) + abs(y_m) + radius_m)
        i0, j0 = self._cell(x_m - reach, y_m - reach)
        i1, j1 = self._cell(x_m + reach, y_m + reach)
        found: list[K] = []
        if (i1 - i0 + 1) * (j1 - j0 + 1) > len(self._cells):
            cells: Iterator[set[K]] = (
                bucket for (i, j), bucket in self._cells.items() if i0 <= i <= i1 and j0 <= j <= j1
            )
        else:
            cells = (
                bucket
                for i in range(i0, i1 + 1)
                for j in range(j0, j1 + 1)
                if (bucket := self._cells.get((i, j))) is not None
            )
        for bucket in cells:
            for key in bucket:
                kx, ky, _ = self._where[key]
                dx, dy = kx - x_m, ky - y_m
                if math.hypot(dx, dy) <= radius_m:  # no underflow, unlike dx² + dy²
                    found.append(key)
        return found
