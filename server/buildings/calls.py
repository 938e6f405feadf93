"""What the API asks of a building besides its batches, each a typed call: its arguments, what it answers,
and which part of the building's host runs it. A call is run on the building's thread in order with its
batches (``BuildingHandle.ask``), and crosses to a building's process or a cluster's worker as it is (a frozen
dataclass pickles), so mypy checks each call's name, arguments and answer end to end."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Generic, TypeVar

from schemas.anchors import BuildingAnchor, KnownAnchorIn
from schemas.floor_plans import FloorPlan
from schemas.live import LiveMessage
from schemas.zones import Zone, ZoneIn
from server.ingestion.convert import BuildingContext

if TYPE_CHECKING:
    from server.buildings.host import BuildingHost

T = TypeVar("T", covariant=True)


class Call(Generic[T]):
    """A request to a building, answered with a ``T``."""

    def run(self, host: BuildingHost) -> T:
        raise NotImplementedError


@dataclass(frozen=True)
class ListAnchors(Call[list[BuildingAnchor]]):
    def run(self, host: BuildingHost) -> list[BuildingAnchor]:
        return host.anchor_edits.anchors()


@dataclass(frozen=True)
class GetAnchor(Call[BuildingAnchor]):
    anchor_id: str

    def run(self, host: BuildingHost) -> BuildingAnchor:
        return host.anchor_edits.get(self.anchor_id)


@dataclass(frozen=True)
class PinAnchor(Call[tuple[BuildingAnchor, list[LiveMessage]]]):
    anchor_id: str
    body: KnownAnchorIn

    def run(self, host: BuildingHost) -> tuple[BuildingAnchor, list[LiveMessage]]:
        return host.anchor_edits.put_known(self.anchor_id, self.body)


@dataclass(frozen=True)
class DeleteAnchor(Call[list[LiveMessage]]):
    anchor_id: str

    def run(self, host: BuildingHost) -> list[LiveMessage]:
        return host.anchor_edits.delete(self.anchor_id)


@dataclass(frozen=True)
class MergeAnchors(Call[tuple[BuildingAnchor, list[LiveMessage]]]):
    anchor_ids: tuple[str, ...]

    def run(self, host: BuildingHost) -> tuple[BuildingAnchor, list[LiveMessage]]:
        return host.anchor_edits.merge(list(self.anchor_ids))


@dataclass(frozen=True)
class PutFloorPlan(Call[FloorPlan]):
    level: int
    body: FloorPlan

    def run(self, host: BuildingHost) -> FloorPlan:
        return host.floor_plans.put(self.level, self.body)


@dataclass(frozen=True)
class PutZone(Call[Zone]):
    zone_id: str
    body: ZoneIn

    def run(self, host: BuildingHost) -> Zone:
        return host.zones.put(self.zone_id, self.body)


@dataclass(frozen=True)
class DeleteZone(Call[None]):
    zone_id: str

    def run(self, host: BuildingHost) -> None:
        host.zones.delete(self.zone_id)


@dataclass(frozen=True)
class ForgetUser(Call[list[LiveMessage]]):
    user_id: str

    def run(self, host: BuildingHost) -> list[LiveMessage]:
        return host.users.forget(self.user_id)


@dataclass(frozen=True)
class AssignDevice(Call[None]):
    device_id: str
    user_id: str

    def run(self, host: BuildingHost) -> None:
        host.users.assign_device(self.device_id, self.user_id)


@dataclass(frozen=True)
class LoadRadioMap(Call["tuple[str, int] | None"]):
    """The latest finished signal-map build's radio map joins the tracker's fingerprints (``None``: none
    newer to load)."""

    def run(self, host: BuildingHost) -> tuple[str, int] | None:
        return host.load_radio_map()


@dataclass(frozen=True)
class ConversionContext(Call[BuildingContext]):
    """What converting the building's batches needs of it now (a signal-map build converts its recordings)."""

    def run(self, host: BuildingHost) -> BuildingContext:
        return host.building.context()


@dataclass(frozen=True)
class FlushRecording(Call[None]):
    """The recording's chunk in progress written now (before a signal-map build reads the recordings)."""

    def run(self, host: BuildingHost) -> None:
        host.upkeep.flush_recording()
