"""The building process reads the front's frames in large chunks (``FrameReader``): every frame comes back
whole and in order however the bytes arrive (split anywhere, many in one read, larger than a read), ``ready``
waits no longer than it is told (a group's linger), ``pending`` sees a frame begun, and the other end going
away ends the stream (mid-frame too)."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest

from server.buildings.process import _NONE, FrameReader, _frame


def _frames(n: int) -> list[tuple[str, int, bytes]]:
    rng = np.random.default_rng(3)
    return [("batch", i, rng.bytes(int(rng.integers(0, 3_000)))) for i in range(n)]


@pytest.mark.parametrize("piece", [1, 7, 4_096, 1 << 22])
def test_frames_come_back_whole_and_in_order_however_the_bytes_arrive(piece: int) -> None:
    messages = _frames(60)
    if piece > 100:  # and one larger than a read (byte by byte it would take long)
        messages.append(("batch", 60, b"x" * (3 * FrameReader.CHUNK)))
    wire = b"".join(_frame(m) for m in messages)
    front, building = socket.socketpair()

    def send() -> None:
        for i in range(0, len(wire), piece):
            front.sendall(wire[i : i + piece])
        front.close()

    sender = threading.Thread(target=send)
    sender.start()
    reader = FrameReader(building)
    got = []
    while (frame := reader.next()) is not None:
        got.append(frame)
    sender.join()
    building.close()
    assert got == messages


def test_ready_never_waits_and_sees_what_arrived() -> None:
    front, building = socket.socketpair()
    reader = FrameReader(building)
    assert reader.ready() is _NONE  # nothing sent: no wait
    first, second = _frames(2)
    front.sendall(_frame(first) + _frame(second)[:5])
    assert reader.ready() == first
    assert reader.ready() is _NONE  # half a frame is not a frame
    front.sendall(_frame(second)[5:])
    assert reader.ready() == second
    front.close()
    assert reader.ready() is None
    assert reader.next() is None
    building.close()


def test_a_frame_cut_off_by_the_other_end_going_away_ends_the_stream() -> None:
    front, building = socket.socketpair()
    (message,) = _frames(1)
    front.sendall(_frame(message) + _frame(message)[:-3])
    front.close()
    reader = FrameReader(building)
    assert reader.next() == message
    assert reader.next() is None
    building.close()


def test_ready_waits_its_timeout_for_a_frame_and_no_longer() -> None:
    front, building = socket.socketpair()
    reader = FrameReader(building)
    first, second = _frames(2)
    started = time.monotonic()
    assert reader.ready(0.15) is _NONE
    assert time.monotonic() - started >= 0.15
    wire = _frame(first)
    # a frame that arrives in two pieces within the wait is taken whole, as soon as it is complete
    sender = threading.Timer(0.05, lambda: front.sendall(wire[:3]))
    rest = threading.Timer(0.1, lambda: front.sendall(wire[3:]))
    sender.start()
    rest.start()
    started = time.monotonic()
    assert reader.ready(5.0) == first
    assert time.monotonic() - started < 2.0
    sender.join()
    rest.join()
    assert not reader.pending()
    front.sendall(_frame(second)[:4])
    assert reader.ready() is _NONE
    assert reader.pending()  # begun, not whole
    front.sendall(_frame(second)[4:])
    assert reader.pending()
    assert reader.ready(1.0) == second
    assert not reader.pending()
    front.close()
    assert reader.ready(1.0) is None
    building.close()
