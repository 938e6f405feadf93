"""A building's public anchor ids: the names operators and the API use for the crowd map's anchor indices."""

from __future__ import annotations

from slam_core.crowd.anchor_map import CrowdMapBuilder


class AnchorIds:
    """Public id <-> crowd index, with each anchor's label. Anchors the crowd found get ``a-<n>`` ids when
    first shown; operators name the anchors they pin."""

    def __init__(self) -> None:
        self.public: dict[int, str] = {}  # crowd index -> public id
        self.index: dict[str, int] = {}  # public id -> crowd index
        self.labels: dict[int, str | None] = {}
        self._next = 0

    def link(self, index: int, public_id: str, label: str | None) -> None:
        self.public[index] = public_id
        self.index[public_id] = index
        self.labels[index] = label
        if public_id.startswith("a-") and public_id[2:].isdigit():
            self._next = max(self._next, int(public_id[2:]) + 1)

    def public_id(self, index: int) -> str:
        """The anchor's public id, a new ``a-<n>`` the first time it is asked for."""
        if index not in self.public:
            while f"a-{self._next}" in self.index:
                self._next += 1
            self.link(index, f"a-{self._next}", None)
        return self.public[index]

    def known_levels(self, crowd: CrowdMapBuilder) -> dict[str, int]:
        """The floors of the live pinned anchors not on floor 0, by public id."""
        levels = {}
        for public_id, index in self.index.items():
            if crowd.is_live(index) and crowd.anchor(index)[3] and crowd.level(index) != 0:
                levels[public_id] = crowd.level(index)
        return levels

    def known_positions(self, crowd: CrowdMapBuilder) -> dict[str, tuple[float, float]]:
        """The live anchors operators pinned, by public id: where converting a batch finds an anchor reading's
        position."""
        known = {}
        for public_id, index in self.index.items():
            if crowd.is_live(index):
                mean, _, _, is_known, _, _ = crowd.anchor(index)
                if is_known:
                    known[public_id] = (float(mean[0]), float(mean[1]))
        return known
