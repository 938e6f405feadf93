"""A building's devices as the batch path needs them: which batches are late, which tracker call applies
each, and which device rows SQL must learn.

A batch whose ``seq`` is not after its device's last applied one is late: recorded, never applied (filters
cannot rewind). Sequence numbers count within an install (``SensorBatch.install_ms``): a batch of a later
install starts its device's count again (a reinstalled phone posts from 0 with no operator action), and a
batch of an earlier install is late whatever its ``seq``. A batch without ``install_ms`` counts in the
device's current install. A device's batches in one group are applied one per tracker call, in order. Both
are decided before anything is written, so each batch row is inserted with the tracker call that will apply
it (the log a restart replays) and no update follows. Device rows are written when a device appears or its
user or Bluetooth id changes; the last applied sequence numbers are written with each tracker snapshot, and
a restart takes the newer ones from the batches it replays.
"""

from __future__ import annotations

from dataclasses import dataclass

from server.buildings.submissions import BatchHeader


@dataclass
class _Device:
    user_id: str
    ble_advertised_id: str | None
    last_seq: int | None
    stored_seq: int | None
    install_ms: int | None = None
    stored_install_ms: int | None = None


def _place(install_ms: int | None, current: int | None) -> str:
    """Where a batch's install stands against its device's current one: "same", "newer" or "older"."""
    if install_ms is None or install_ms == current:
        return "same"
    if current is None or install_ms > current:
        return "newer"
    return "older"


class DeviceLedger:
    def __init__(
        self, building_id: str, rows: dict[str, tuple[str, str | None, int | None, int | None]]
    ) -> None:
        """``rows``: the building's stored devices, id -> (user id, Bluetooth id, last applied seq, its
        install)."""
        self.building_id = building_id
        self._devices = {
            d: _Device(u, ble, seq, seq, install, install) for d, (u, ble, seq, install) in rows.items()
        }

    def user_of(self, device_id: str) -> str | None:
        """The user a device posts as (None: a device not seen yet)."""
        device = self._devices.get(device_id)
        return None if device is None else device.user_id

    def may_post_as(self, device_id: str, user_id: str) -> bool:
        """A device posts for its own id, or for the user it has posted as (or an operator assigned it). A
        device not seen yet may take a user no other device posts as and no other device is named."""
        if user_id == device_id:
            return True
        current = self.user_of(device_id)
        if current is not None:
            return current == user_id
        return user_id not in self._devices and all(d.user_id != user_id for d in self._devices.values())

    def assign(self, device_id: str, user_id: str) -> dict[str, object]:
        """An operator's assignment of a device to a user; returns the device's row for SQL."""
        device = self._devices.get(device_id)
        if device is None:
            self._devices[device_id] = _Device(user_id, None, None, None)
        else:
            device.user_id = user_id
        return self._row(device_id)

    def last_seq(self, device_id: str) -> int | None:
        device = self._devices.get(device_id)
        return None if device is None else device.last_seq

    def plan(self, batches: list[BatchHeader]) -> list[int | None]:
        """Per batch (in arrival order): the tracker call of this group that applies it (1, 2, ...: a user's
        k-th batch here goes in the k-th call) or None when it is late. Nothing is recorded yet."""
        last: dict[str, tuple[int | None, int | None]] = {}  # device -> (install, seq) so far in the group
        calls: dict[str, int] = {}
        out: list[int | None] = []
        for b in batches:
            device = self._devices.get(b.device_id)
            install, previous = last.get(
                b.device_id, (None, None) if device is None else (device.install_ms, device.last_seq)
            )
            place = _place(b.install_ms, install)
            if place == "older" or (place == "same" and previous is not None and b.seq <= previous):
                out.append(None)
                continue
            last[b.device_id] = (b.install_ms if place == "newer" else install, b.seq)
            user = b.effective_user_id
            calls[user] = calls.get(user, 0) + 1
            out.append(calls[user])
        return out

    def applied(self, batch: BatchHeader) -> dict[str, object] | None:
        """Record an applied batch; returns the device's row when SQL must learn it now (a new device, or
        a new user or Bluetooth id; a batch without a Bluetooth id keeps the stored one), else None."""
        device = self._devices.get(batch.device_id)
        ble = batch.ble_advertised_id
        if device is None:
            self.replayed(batch)  # a new device, as a replayed batch makes one
            return self._row(batch.device_id)
        changed = device.user_id != batch.effective_user_id or (
            ble is not None and ble != device.ble_advertised_id
        )
        device.user_id = batch.effective_user_id
        device.ble_advertised_id = ble if ble is not None else device.ble_advertised_id
        _count(device, batch)
        if not changed:
            return None
        return self._row(batch.device_id)

    def replayed(self, batch: BatchHeader) -> None:
        """A logged batch re-applied after a restart: its device's last seq moves on (SQL learns it at the
        next snapshot)."""
        device = self._devices.get(batch.device_id)
        if device is None:
            self._devices[batch.device_id] = _Device(
                batch.effective_user_id, batch.ble_advertised_id, batch.seq, None, batch.install_ms, None
            )
        else:
            _count(device, batch)

    def unsaved_rows(self) -> list[dict[str, object]]:
        """The rows of devices whose last seq SQL does not have yet (``saved`` once they are committed)."""
        return [
            self._row(d)
            for d, device in self._devices.items()
            if (device.last_seq, device.install_ms) != (device.stored_seq, device.stored_install_ms)
        ]

    def saved(self, rows: list[dict[str, object]]) -> None:
        """These rows (from ``unsaved_rows`` or ``applied``) are committed."""
        for row in rows:
            device = self._devices[str(row["id"])]
            seq, install = row["last_seq"], row["install_ms"]
            device.stored_seq = seq if isinstance(seq, int) else None
            device.stored_install_ms = install if isinstance(install, int) else None

    def _row(self, device_id: str) -> dict[str, object]:
        device = self._devices[device_id]
        return {
            "building_id": self.building_id,
            "id": device_id,
            "user_id": device.user_id,
            "ble_advertised_id": device.ble_advertised_id,
            "last_seq": device.last_seq,
            "install_ms": device.install_ms,
        }


def _count(device: _Device, batch: BatchHeader) -> None:
    """An applied (or replayed) batch moves its device's count on: from its seq in a later install, else to
    the larger of the two."""
    if _place(batch.install_ms, device.install_ms) == "newer":
        device.install_ms, device.last_seq = batch.install_ms, batch.seq
    elif device.last_seq is None or batch.seq > device.last_seq:
        device.last_seq = batch.seq
