"""A building's extent: where a position in it may be, from its floors' sizes plus the operator's margin."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass


@dataclass(frozen=True)
class Extent:
    """The rectangle of the local frame (metres) that every position posted to a building must fall in: the
    union of its floors' rectangles (``0..width_m`` east, ``0..height_m`` north of the origin) grown by a
    margin on every side. Entrances, car parks and a phone's first fix outside the door lie in the margin;
    a fix a hundred kilometres away is a client's error that would drag its user's filter there."""

    x_min: float
    x_max: float
    y_min: float
    y_max: float
    margin_m: float

    @classmethod
    def of_floors(cls, sizes: Iterable[tuple[float | None, float | None]], margin_m: float) -> Extent | None:
        """The extent of floors given as (width, height); None when no floor has both (the building's size
        is unknown, and only the wire schema's physical bound applies)."""
        known = [(w, h) for w, h in sizes if w is not None and h is not None]
        if not known:
            return None
        width = max(w for w, _ in known)
        height = max(h for _, h in known)
        return cls(-margin_m, width + margin_m, -margin_m, height + margin_m, margin_m)

    def contains(self, x: float, y: float) -> bool:
        return self.x_min <= x <= self.x_max and self.y_min <= y <= self.y_max

    def refusal(self, what: str, x: float, y: float) -> str | None:
        """Why ``what`` at (x, y) is refused, or None when it lies within the extent."""
        if self.contains(x, y):
            return None
        m = self.margin_m
        return (
            f"{what} at ({x:.1f}, {y:.1f}) m is outside the building: its floors span x "
            f"{self.x_min + m:g}..{self.x_max - m:g} m and y {self.y_min + m:g}..{self.y_max - m:g} m, and "
            f"positions may lie at most {m:g} m beyond them (CROWDSLAM_EXTENT_MARGIN_M)"
        )
