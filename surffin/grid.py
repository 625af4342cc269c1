"""The sensor grid: rectangles of pixels (crop, rois) shared by every layer."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

__all__ = ["Roi"]


@dataclass(frozen=True)
class Roi:
    """A rectangle of sensor pixels: half-open row and column ranges.

    Attributes
    ----------
    y : (int, int)
        ``[start, stop)`` sensor rows.
    x : (int, int)
        ``[start, stop)`` sensor columns.
    """

    y: tuple[int, int]
    x: tuple[int, int]

    @property
    def slices(self) -> tuple[slice, slice]:
        """``(rows, columns)`` slices of a (height, width) sensor image."""
        return slice(*self.y), slice(*self.x)

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, columns)`` in pixels."""
        return self.y[1] - self.y[0], self.x[1] - self.x[0]

    def grown(self, margin: int) -> Roi:
        """Return this roi with ``margin`` more pixels on every side (clip it to the grid it is on)."""
        return Roi((self.y[0] - margin, self.y[1] + margin), (self.x[0] - margin, self.x[1] + margin))

    def clip(self, other: Roi) -> Roi:
        """Return the part of this roi inside ``other``.

        Raises
        ------
        ValueError
            The two do not overlap.
        """
        y = (max(self.y[0], other.y[0]), min(self.y[1], other.y[1]))
        x = (max(self.x[0], other.x[0]), min(self.x[1], other.x[1]))
        if y[0] >= y[1] or x[0] >= x[1]:
            raise ValueError(f"{self} does not overlap {other}")
        return Roi(y, x)

    @classmethod
    def from_mapping(cls, roi: Mapping | Roi | None) -> Roi | None:
        """Build a Roi from its ``{"y": [a, b], "x": [c, d]}`` form (a store's attrs, a job's parameters)."""
        if roi is None or isinstance(roi, Roi):
            return roi
        return cls(tuple(roi["y"]), tuple(roi["x"]))

    @classmethod
    def spanning(cls, y: Sequence[int], x: Sequence[int]) -> Roi:
        """Return the smallest roi that holds the sensor rows ``y`` and columns ``x`` (a grid's coordinates)."""
        return cls((int(min(y)), int(max(y)) + 1), (int(min(x)), int(max(x)) + 1))

    def as_mapping(self) -> dict[str, list[int]]:
        """Return the ``{"y": [a, b], "x": [c, d]}`` form, for JSON and YAML."""
        return {"y": list(self.y), "x": list(self.x)}
