"""Prometheus metrics: counters from the buildings' tracking, gauges from queues, latency summaries."""

from __future__ import annotations

import time
from dataclasses import fields
from typing import TYPE_CHECKING

import numpy as np
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from server.buildings.counters import Counters
from server.buildings.registry import Buildings, failing_buildings
from server.live.broadcast import Broadcaster
from server.storage import Storage

if TYPE_CHECKING:
    from collections.abc import Iterator


class Metrics:
    """Renders the current figures on each scrape (no global registry: one per app)."""

    def render(self, tracking: Buildings, broadcaster: Broadcaster, storage: Storage) -> bytes:
        registry = CollectorRegistry()
        registry.register(_Collector(tracking, broadcaster, storage))
        return bytes(generate_latest(registry))


class _Collector(Collector):
    def __init__(self, tracking: Buildings, broadcaster: Broadcaster, storage: Storage) -> None:
        self._tracking = tracking
        self._broadcaster = broadcaster
        self._storage = storage

    def collect(self) -> Iterator[Metric]:

        handles = self._tracking.handles
        for f in fields(Counters):
            family = CounterMetricFamily(
                f"crowdslam_{f.name}", f"{f.name.replace('_', ' ')} per building", labels=["building"]
            )
            for building, handle in handles.items():
                counters: Counters = handle.counters
                family.add_metric([building], float(getattr(counters, f.name)))
            yield family
        depth = GaugeMetricFamily(
            "crowdslam_ingest_queue_depth", "batches waiting per building", labels=["building"]
        )
        latency = GaugeMetricFamily(
            "crowdslam_group_latency_seconds",
            "processing time of a group of batches (recent window)",
            labels=["building", "quantile"],
        )
        for building, handle in handles.items():
            depth.add_metric([building], float(handle.queue_depth))
            values = handle.latency.values
            if values:
                for q in (0.5, 0.99):
                    latency.add_metric([building, str(q)], float(np.quantile(values, q)))
        yield depth
        yield latency
        failing = GaugeMetricFamily(
            "crowdslam_building_failing",
            "1 while a building cannot be loaded or failed a batch lately (as /healthz's failing_buildings)",
            labels=["building"],
        )
        load_failures = GaugeMetricFamily(
            "crowdslam_building_load_failures",
            "attempts in a row to load a building that failed (0 once it loads)",
            labels=["building"],
        )
        for trouble in failing_buildings(self._tracking, time.time()):
            failing.add_metric([trouble.building_id], 1.0)
            load_failures.add_metric([trouble.building_id], float(trouble.failed_loads))
        yield failing
        yield load_failures
        subs = GaugeMetricFamily("crowdslam_live_subscribers", "open live WebSocket subscriptions")
        subs.add_metric([], float(self._broadcaster.subscribers()))
        yield subs
        backlog = GaugeMetricFamily("crowdslam_live_queue_max", "longest live subscriber queue")
        backlog.add_metric([], float(max(self._broadcaster.queue_depths(), default=0)))
        yield backlog
        published = CounterMetricFamily("crowdslam_live_messages", "live messages published")
        published.add_metric([], float(self._broadcaster.published))
        yield published
        for name, text, value in (
            ("crowdslam_data_dir_bytes", "bytes under the data directory", self._storage.data_dir_bytes),
            ("crowdslam_database_bytes", "bytes of the database", self._storage.database_bytes),
            (
                "crowdslam_disk_free_bytes",
                "free bytes on the data directory's disk",
                self._storage.free_bytes,
            ),
        ):
            gauge = GaugeMetricFamily(name, text)
            gauge.add_metric([], float(value))
            yield gauge
