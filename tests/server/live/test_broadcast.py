"""The live fan-out: every subscriber gets every message in order, in chunks of at most MAX_LIVE_BATCH;
a slow one loses the oldest, counted; a wait ends with what came or with nothing at the timeout."""

from __future__ import annotations

import asyncio
import json

import pytest

from schemas.anchors import ANCHOR_EXAMPLE, BuildingAnchor
from schemas.estimates import ESTIMATE_EXAMPLE, EncounterEvent, Estimate
from schemas.live import (
    LIVE_MESSAGE_ADAPTER,
    MAX_LIVE_BATCH,
    AnchorMessage,
    EncounterMessage,
    HeartbeatMessage,
    LiveBatch,
    LiveMessage,
    PositionMessage,
)
from server.live.broadcast import QUEUE_SIZE, Broadcaster, Chunk, chunks_of, live_json


def _texts(n: int, start: int = 0) -> list[str]:
    return [json.dumps({"type": "heartbeat", "t_ms": 1_767_225_600_000 + i}) for i in range(start, start + n)]


def _received(chunks: list[Chunk]) -> list[str]:
    return [t for c in chunks for t in c.texts]


def test_chunks_cut_at_the_frame_bound_and_join_their_texts() -> None:
    texts = _texts(2 * MAX_LIVE_BATCH + 3)
    chunks = chunks_of(texts)
    assert [len(c.texts) for c in chunks] == [MAX_LIVE_BATCH, MAX_LIVE_BATCH, 3]
    assert _received(chunks) == texts
    for c in chunks:
        assert json.loads("[" + c.joined + "]") == [json.loads(t) for t in c.texts]
    assert chunks_of([]) == []


def test_every_subscriber_gets_every_message_in_order_and_a_frame_holds_at_most_the_bound() -> None:
    broadcaster = Broadcaster()
    subs = [broadcaster.subscribe("hq"), broadcaster.subscribe("hq")]
    other = broadcaster.subscribe("elsewhere")
    sent: list[str] = []
    for n in [3, MAX_LIVE_BATCH - 2, 5, 1]:
        texts = _texts(n, start=len(sent))
        broadcaster.publish_texts("hq", texts)
        sent += texts
    assert broadcaster.published == len(sent)
    assert other.queued == 0
    assert other.take() == []
    for sub in subs:
        assert sub.queued == len(sent)
        frames = []
        while sub.queued:
            frames.append(sub.take())
        assert all(sum(len(c.texts) for c in f) <= MAX_LIVE_BATCH for f in frames)
        assert [t for f in frames for t in _received(f)] == sent
        assert sub.dropped == 0
        # a frame of whole chunks is a valid LiveBatch
        body = '{"type":"batch","messages":[' + ",".join(c.joined for c in frames[0]) + "]}"
        assert len(LiveBatch.model_validate_json(body).messages) == sum(len(c.texts) for c in frames[0])


def test_a_slow_subscriber_loses_the_oldest_messages_and_counts_them() -> None:
    broadcaster = Broadcaster()
    sub = broadcaster.subscribe("hq")
    sent: list[str] = []
    for _ in range(5):
        texts = _texts(700, start=len(sent))
        broadcaster.publish_texts("hq", texts)
        sent += texts
    assert sub.queued <= QUEUE_SIZE
    assert sub.dropped + sub.queued == len(sent) == 3_500
    kept = []
    while sub.queued:
        kept += _received(sub.take())
    assert kept == sent[sub.dropped :]  # the newest, in order
    assert broadcaster.queue_depths() == [0]


def test_publish_serialises_the_messages_once_and_unsubscribed_get_nothing() -> None:
    broadcaster = Broadcaster()
    sub = broadcaster.subscribe("hq")
    gone = broadcaster.subscribe("hq")
    broadcaster.unsubscribe(gone)
    message = HeartbeatMessage(t_ms=1_767_225_600_000, dropped=2)
    broadcaster.publish("hq", [message])
    (chunk,) = sub.take()
    assert LIVE_MESSAGE_ADAPTER.validate_json(chunk.texts[0]) == message
    assert gone.queued == 0
    assert broadcaster.subscribers("hq") == 1


def test_next_returns_what_came_or_nothing_at_the_timeout() -> None:
    async def scenario() -> None:
        broadcaster = Broadcaster()
        sub = broadcaster.subscribe("hq")
        assert await sub.next(0.01) == []
        waiting = asyncio.create_task(sub.next(5.0))
        await asyncio.sleep(0)
        broadcaster.publish_texts("hq", _texts(2))
        assert _received(await asyncio.wait_for(waiting, 1.0)) == _texts(2)
        assert await sub.next(0.01) == []  # taken: nothing waits any more

    asyncio.run(scenario())


@pytest.mark.parametrize("n", [0, 1, MAX_LIVE_BATCH, MAX_LIVE_BATCH + 1])
def test_counts_stay_consistent(n: int) -> None:
    broadcaster = Broadcaster()
    sub = broadcaster.subscribe("hq")
    broadcaster.publish_texts("hq", _texts(n))
    assert sub.queued == n == broadcaster.published
    taken = 0
    while sub.queued:
        taken += sum(len(c.texts) for c in sub.take())
    assert taken == n


def test_live_json_is_what_the_union_adapter_gives_for_every_message_type() -> None:
    estimate = Estimate.model_validate(ESTIMATE_EXAMPLE)
    encounter = EncounterEvent(
        building_id="hq", t_ms=1_767_225_600_000, user_a="a", user_b="b", model="bluetooth",
        distance_m=2.5, distance_sigma_m=1.1, applied=True,
    )  # fmt: skip
    messages: list[LiveMessage] = [
        PositionMessage(estimate=estimate),
        PositionMessage(estimate=estimate.model_copy(update={"best_particle": None, "lat_deg": None})),
        EncounterMessage(encounter=encounter),
        AnchorMessage(anchor=BuildingAnchor.model_validate(ANCHOR_EXAMPLE), deleted=True),
        HeartbeatMessage(t_ms=1_767_225_600_000, dropped=3),
    ]
    for message in messages:
        assert live_json(message) == LIVE_MESSAGE_ADAPTER.dump_json(message).decode()
        assert LIVE_MESSAGE_ADAPTER.validate_json(live_json(message)) == message
