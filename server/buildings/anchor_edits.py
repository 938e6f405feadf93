"""An operator's edits of a building's anchor map: pin an anchor (new, or a learned one made exact), move it,
delete it, merge anchors the crowd learned twice. Each edit changes the tracker, and the anchor rows and a
snapshot are written in one transaction: a restart replays the batches after the edit on the edited map and
none before it; a transaction that fails leaves the building as SQL holds it (reloaded)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from sqlalchemy.orm import Session

from schemas.anchors import BuildingAnchor, KnownAnchorIn
from schemas.live import AnchorMessage, LiveMessage
from server.buildings.building import Building, SaveSnapshot, commit_with_snapshot
from server.buildings.rows import anchor_row
from server.errors import ConflictError, InvalidInputError
from server.ingestion import convert
from server.store import repositories as repo


class AnchorEdits:
    def __init__(self, building: Building, save_snapshot: SaveSnapshot, reload: Callable[[], None]) -> None:
        self.building = building
        self._save_snapshot = save_snapshot
        self._reload = reload

    def anchors(self) -> list[BuildingAnchor]:
        """Every live anchor, by crowd index."""
        b = self.building
        return [b.anchor(i) for i in sorted(b.ids.public) if b.tracker.crowd.is_live(i)]

    def get(self, public_id: str) -> BuildingAnchor:
        return self.building.anchor(self.building.live_anchor(public_id))

    def put_known(self, public_id: str, body: KnownAnchorIn) -> tuple[BuildingAnchor, list[LiveMessage]]:
        """Pin an anchor at an exact place: a new one, or one of the crowd's made exact, or moved. Asked
        again exactly as it is (a retry), it changes nothing."""
        b = self.building
        index = b.ids.index.get(public_id)
        if index is not None and not b.tracker.crowd.is_live(index):
            raise ConflictError(f"anchor {public_id!r} was deleted or merged; pick a new id")
        if b.extent is not None:
            refusal = b.extent.refusal("the anchor", body.position.x_m, body.position.y_m)
            if refusal is not None:
                raise InvalidInputError(refusal)
        if body.floor not in b.tracker.levels:
            raise InvalidInputError(
                f"building {b.building_id!r} has no floor {body.floor}; its floors: "
                f"{', '.join(map(str, b.tracker.levels))}"
            )
        xy = np.array([body.position.x_m, body.position.y_m])
        type_index = convert.anchor_type_index(body.type)
        if index is not None and self._pinned_as(index, xy, type_index, body):
            return b.anchor(index), []
        index = b.tracker.pin_anchor(xy, type_index, index, level=body.floor)
        b.ids.link(index, public_id, body.label)
        anchor = b.anchor(index)
        self._commit(lambda session: repo.save_anchor(session, anchor_row(b.building_id, anchor)))
        return anchor, [AnchorMessage(anchor=anchor)]

    def _pinned_as(self, index: int, xy: np.ndarray, type_index: int, body: KnownAnchorIn) -> bool:
        """Whether the anchor is pinned already exactly as ``body`` asks."""
        b = self.building
        mean, _, pinned_type, known, _, _ = b.tracker.crowd.anchor(index)
        return (
            known
            and pinned_type == type_index
            and bool(np.array_equal(mean, xy))
            and b.tracker.crowd.level(index) == body.floor
            and b.ids.labels.get(index) == body.label
        )

    def delete(self, public_id: str) -> list[LiveMessage]:
        b = self.building
        index = b.live_anchor(public_id)
        anchor = b.anchor(index)
        b.tracker.remove_anchor(index)
        self._commit(lambda session: repo.delete_anchor(session, b.building_id, public_id))
        return [AnchorMessage(anchor=anchor, deleted=True)]

    def merge(self, public_ids: list[str]) -> tuple[BuildingAnchor, list[LiveMessage]]:
        """Merge anchors the crowd learned twice into the first; 409 when one of them is not live (deleted,
        or merged already: a retry finds it so)."""
        b = self.building
        if len(set(public_ids)) != len(public_ids):
            raise InvalidInputError("anchor_ids must be distinct")
        live = {p: b.ids.index.get(p) for p in public_ids}
        missing = [p for p, i in live.items() if i is None or not b.tracker.crowd.is_live(i)]
        if missing:
            raise ConflictError(
                f"no live anchor {', '.join(map(repr, missing))} in building {b.building_id!r}; "
                "nothing was merged"
            )
        olds = [b.anchor(b.ids.index[p]) for p in public_ids]
        keep = b.ids.index[public_ids[0]]
        for p in public_ids[1:]:
            b.tracker.merge_anchors(keep, b.ids.index[p])
        merged = b.anchor(keep)

        def write(session: Session) -> None:
            repo.save_anchor(session, anchor_row(b.building_id, merged))
            for p in public_ids[1:]:
                repo.delete_anchor(session, b.building_id, p)

        self._commit(write)
        messages: list[LiveMessage] = [AnchorMessage(anchor=merged)]
        messages += [AnchorMessage(anchor=a, deleted=True) for a in olds[1:]]
        return merged, messages

    def _commit(self, write: Callable[[Session], object]) -> None:
        commit_with_snapshot(self.building, self._save_snapshot, self._reload, write)
