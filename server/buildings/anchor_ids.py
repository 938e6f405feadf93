"""A building's public anchor ids: the names operators and the API use for the crowd map's anchor indices."""

from __future__ import annotations


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
