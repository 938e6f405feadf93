"""Cluster mode on the local PostgreSQL and a private NATS: fronts and workers as real processes, phones
posting through the fronts while a worker is killed with ``kill -9``, a front is killed, NATS restarts, or a
worker joins. Whatever happens, every acknowledged batch is in the store, no batch is applied twice, each
device's batches apply in order (none answers ``late``), and users stay tracked without a new fix."""

from __future__ import annotations

import json
import threading
import time
from collections import Counter
from pathlib import Path

import httpx
from websockets.sync.client import connect as websocket

from tests.server.cluster.cluster import LEASE_TTL_S, Cluster, Crowd, local_cluster, small_crowd

BUILDINGS = ["mall:north", "mall.south", "hq", "depot"]  # ids with a ':' and a '.', as NATS names must bear


def _check_nothing_lost_or_doubled(cluster: Cluster, crowd: Crowd) -> None:
    acknowledged = crowd.acknowledged()
    posted = {(b, x.device_id, x.batch_id) for b in crowd.buildings for x in crowd.batches[b]}
    assert {(a.building, a.device_id, a.batch_id) for a in acknowledged} == posted  # every phone got through
    assert cluster.stored_batches() == posted  # and everything acknowledged is in the store
    applied = Counter(
        (a.building, a.device_id, a.batch_id) for a in acknowledged if a.receipt.status == "applied"
    )  # type: ignore[union-attr]
    assert max(applied.values()) == 1, "a batch was applied twice"
    statuses = Counter(a.receipt.status for a in acknowledged)  # type: ignore[union-attr]
    assert statuses["late"] == 0, f"batches applied out of their device's order: {statuses}"
    # a retry of an acknowledged batch (its answer lost) is recognised, whichever worker holds the building
    for building in crowd.buildings:
        for batch in crowd.batches[building][:: max(1, len(crowd.batches[building]) // 6)]:
            assert crowd.post_again(building, batch).status == "duplicate"


class Dashboard:
    """A dashboard on one front, noting the devices whose positions it is sent."""

    def __init__(self, front: str, building: str, operator: str) -> None:
        with httpx.Client(base_url=front, timeout=30.0) as client:
            created = client.post(
                f"/v1/buildings/{building}/keys",
                json={"scope": "dashboard"},
                headers={"Authorization": f"Bearer {operator}"},
            )
        self.key = created.json()["key"]
        self.url = front.replace("http://", "ws://") + f"/v1/buildings/{building}/live"
        self.seen: set[str] = set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch)

    def __enter__(self) -> Dashboard:
        self._thread.start()
        time.sleep(0.5)
        return self

    def __exit__(self, *_: object) -> None:
        time.sleep(1.0)
        self._stop.set()
        self._thread.join()

    def _watch(self) -> None:
        with websocket(self.url, subprotocols=["crowdslam.live", f"bearer.{self.key}"]) as socket:  # type: ignore[list-item]
            while not self._stop.is_set():
                try:
                    frame = socket.recv(timeout=0.5)
                except TimeoutError:
                    continue
                for line in str(frame).splitlines():
                    message = json.loads(line)
                    if message.get("type") == "position":
                        self.seen.add(message["estimate"]["device_id"])


def test_two_fronts_and_two_workers_serve_four_buildings_and_a_worker_killed_loses_nothing(
    tmp_path: Path,
) -> None:
    with local_cluster(tmp_path, fronts=2, workers=2) as cluster:
        crowd = Crowd(cluster, small_crowd(), BUILDINGS)
        crowd.prepare()
        owners = cluster.wait_until_shared(workers=2)
        assert Counter(owners.values()) == {cluster.workers[0].pid: 2, cluster.workers[1].pid: 2}
        victim = cluster.workers[0]
        taken_over = sorted(b for b, pid in owners.items() if pid == victim.pid)
        killed_at: list[float] = []

        def kill_midway(done: float) -> None:
            if done >= 0.4 and not killed_at:
                killed_at.append(time.time())
                cluster.kill(victim)

        # a dashboard on the first front sees the positions of phones posting through the second
        with Dashboard(cluster.front_urls()[0], "hq", cluster.operator) as dashboard:
            crowd.post(every_s=0.02, on_progress=kill_midway)
        assert dashboard.seen == set(crowd.keys["hq"])  # phones 0 and 2 post through one front, 1 the other
        assert killed_at
        assert len(taken_over) == 2
        _check_nothing_lost_or_doubled(cluster, crowd)
        assert set(cluster.owner_pids().values()) == {cluster.workers[1].pid}
        # the users of the buildings taken over are tracked on, from the snapshot and the batch log: no batch
        # after the kill carries a fix, yet each one's receipt has an estimate
        after = [
            a
            for a in crowd.acknowledged()
            if a.building in taken_over and a.at > killed_at[0] + 0.5 and a.receipt.status == "applied"  # type: ignore[union-attr]
        ]
        assert after
        assert all(a.receipt.tracking and a.receipt.estimate is not None for a in after)  # type: ignore[union-attr]
        # the takeover: within the lease's TTL, the balancing period and the building's restore (the phones
        # of those buildings waited for it, with or without a 503 on the way)
        moved = sorted(a.at for a in crowd.answers if a.building in taken_over and a.at > killed_at[0])
        assert moved
        gaps = [later - earlier for earlier, later in zip([killed_at[0], *moved], moved, strict=False)]
        assert max(gaps) < LEASE_TTL_S + 10.0, max(gaps)


def test_a_front_killed_the_phones_go_to_the_other(tmp_path: Path) -> None:
    with local_cluster(tmp_path, fronts=2, workers=1) as cluster:
        crowd = Crowd(cluster, small_crowd(), BUILDINGS[:2])
        crowd.prepare()
        cluster.wait_until_shared(workers=1)
        killed: list[bool] = []

        def kill_midway(done: float) -> None:
            if done >= 0.4 and not killed:
                killed.append(True)
                cluster.kill(cluster.fronts[0][1])

        crowd.post(every_s=0.02, on_progress=kill_midway)
        assert killed
        _check_nothing_lost_or_doubled(cluster, crowd)


def test_nats_restarting_loses_nothing_and_an_older_databases_batches_are_not_applied(tmp_path: Path) -> None:
    with local_cluster(tmp_path, fronts=1, workers=1) as cluster:
        crowd = Crowd(cluster, small_crowd(), BUILDINGS[:2])
        crowd.prepare()
        cluster.wait_until_shared(workers=1)
        # a batch left in the stream for an earlier building of the same id: never this building's
        stale = crowd.batches[BUILDINGS[0]][0].model_copy(update={"batch_id": "from-an-older-database"})
        cluster.publish_foreign(BUILDINGS[0], stale)
        restarted: list[bool] = []

        def restart_midway(done: float) -> None:
            if done >= 0.4 and not restarted:
                restarted.append(True)
                threading.Thread(target=cluster.restart_nats).start()

        crowd.post(every_s=0.02, on_progress=restart_midway)
        assert restarted
        _check_nothing_lost_or_doubled(cluster, crowd)


def test_a_worker_that_joins_takes_buildings_over_cleanly(tmp_path: Path) -> None:
    with local_cluster(tmp_path, fronts=1, workers=1) as cluster:
        crowd = Crowd(cluster, small_crowd(), BUILDINGS)
        crowd.prepare()
        cluster.wait_until_shared(workers=1)
        joined: list[bool] = []

        def join_midway(done: float) -> None:
            if done >= 0.3 and not joined:
                joined.append(True)
                threading.Thread(target=cluster.start_worker).start()

        crowd.post(every_s=0.03, on_progress=join_midway)
        owners = cluster.wait_until_shared(workers=2)
        assert Counter(owners.values()) == {cluster.workers[0].pid: 2, cluster.workers[1].pid: 2}
        _check_nothing_lost_or_doubled(cluster, crowd)
        first, second = (
            (cluster.root / "worker-0.log").read_text(),
            (cluster.root / "worker-1.log").read_text(),
        )
        assert first.count("handing") == 2
        # the joining worker started each building from the snapshot its last owner wrote when handing it
        # off: there was no batch log to replay (a replay is what a crash leaves)
        assert second.count("took building") == 2
        assert second.count("(replayed 0 logged batches)") == 2
