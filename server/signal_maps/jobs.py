"""Signal-map builds: one process for SignalSLAM (gtsam holds the GIL), job records on disk.

A job's record (``job.json``) and outputs live in ``<data_dir>/signal_maps/<building>/<job id>/``, so builds
survive a restart; a build still queued or running when the server stops is marked failed at the next start.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import uuid
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from schemas.signal_maps import SignalMapJob, SignalMapStatus
from server.errors import ConflictError, NotFoundError, TooManyRequestsError
from server.ingestion.convert import BuildingContext
from server.ingestion.radio_maps import RECORD
from server.process_lifetime import die_with, interrupts_held
from server.signal_maps.build import build_signal_maps

MAX_PENDING_BUILDS = 4
"""Builds queued or running at once, over all buildings; one more is refused (429) until one ends."""


class SignalMapService:
    def __init__(self, root: Path, recordings: Path | None, modalities: tuple[str, ...] = ("wifi",)) -> None:
        # Called with the building's id when one of its builds is done (from the pool's thread).
        self.on_built: Callable[[str], None] | None = None
        self.root = root
        self.recordings = recordings
        self.modalities = modalities
        self._pool: ProcessPoolExecutor | None = None
        self._futures: dict[str, Future[dict[str, Any]]] = {}
        self._lock = threading.Lock()
        self._fail_interrupted()

    def _folder(self, building_id: str, job_id: str) -> Path:
        return self.root / building_id / job_id

    def _save(self, job: SignalMapJob) -> None:
        _write_record(self._folder(job.building_id, job.id), job)

    def _fail_interrupted(self) -> None:
        for record in self.root.glob(f"*/*/{RECORD}"):
            job = SignalMapJob.model_validate_json(record.read_text())
            if job.status in (SignalMapStatus.QUEUED, SignalMapStatus.RUNNING):
                self._save(job.model_copy(update={
                    "status": SignalMapStatus.FAILED, "finished_at": datetime.now(UTC),
                    "error": "the server stopped before the build finished; start a new one",
                }))  # fmt: skip

    def start(self, ctx: BuildingContext) -> SignalMapJob:
        if self.recordings is None:
            raise ConflictError(
                "recording is switched off (CROWDSLAM_RECORD), so there is nothing to build from"
            )
        files = sorted((self.recordings / ctx.building_id).glob("*.mcap"))
        if not files:
            raise ConflictError(f"building {ctx.building_id!r} has no recordings yet")
        with self._lock:
            if len(self._futures) >= MAX_PENDING_BUILDS:
                raise TooManyRequestsError(
                    f"{len(self._futures)} signal-map builds are queued or running, the most allowed; "
                    "start this one when one has ended",
                    60.0,
                )
        job = SignalMapJob(
            id=uuid.uuid4().hex[:12],
            building_id=ctx.building_id,
            status=SignalMapStatus.QUEUED,
            created_at=datetime.now(UTC),
            recordings=len(files),
        )
        self._save(job)
        with self._lock:
            if self._pool is None:
                self._pool = ProcessPoolExecutor(
                    max_workers=1, mp_context=multiprocessing.get_context("spawn")
                )
            with interrupts_held():  # the pool starts its process on a first submit
                future = self._pool.submit(
                    _run_build,
                    os.getpid(),
                    [str(f) for f in files],
                    str(self._folder(ctx.building_id, job.id)),
                    ctx,
                    self.modalities,
                )
            self._futures[job.id] = future
        future.add_done_callback(lambda f: self._finish(job, f))
        return job

    def _finish(self, job: SignalMapJob, future: Future[dict[str, Any]]) -> None:
        """The build's process recorded how it ended (``_run_build``); a process that died could not, and
        its job is recorded failed here."""
        try:
            future.result()
        except Exception as error:
            if self.get(job.building_id, job.id).status != SignalMapStatus.FAILED:
                self._save(_ended(job, error=error))
        else:
            if self.on_built is not None:
                self.on_built(job.building_id)
        with self._lock:
            self._futures.pop(job.id, None)

    def loaded(self, building_id: str, job_id: str, scans: int) -> None:
        """The building's tracker has loaded build ``job_id``'s radio map: ``scans`` joined."""
        job = self.get(building_id, job_id)
        self._save(job.model_copy(update={"radio_map_scans": scans}))

    def get(self, building_id: str, job_id: str) -> SignalMapJob:
        record = self._folder(building_id, job_id) / RECORD
        if not job_id.isalnum() or not record.is_file():
            raise NotFoundError(f"no signal-map build {job_id!r} for building {building_id!r}")
        return SignalMapJob.model_validate_json(record.read_text())

    def list(self, building_id: str) -> list[SignalMapJob]:
        jobs = [self.get(building_id, r.parent.name) for r in (self.root / building_id).glob(f"*/{RECORD}")]
        return sorted(jobs, key=lambda j: j.created_at, reverse=True)

    def file(self, building_id: str, job_id: str, name: str) -> Path:
        job = self.get(building_id, job_id)
        if name not in job.files:
            raise NotFoundError(
                f"build {job_id!r} has no file {name!r}; it has: {', '.join(job.files) or 'none'}"
            )
        return self._folder(building_id, job_id) / name

    def close(self) -> None:
        with self._lock:
            if self._pool is not None:
                self._pool.shutdown(wait=False, cancel_futures=True)
                self._pool = None


def _run_build(
    server_pid: int, files: list[str], folder: str, ctx: BuildingContext, modalities: tuple[str, ...]
) -> dict[str, Any]:
    """In the build's process: die with the server (a worker left behind by ``kill -9`` would hold a core
    and a job nobody reads), say the job runs (the pool takes a queued job off its queue before it starts,
    so the server cannot tell), build, and say how it ended before the process takes the next job: builds
    run one at a time, so at most one is ever reported running."""
    die_with(server_pid)
    job = SignalMapJob.model_validate_json((Path(folder) / RECORD).read_text())
    _write_record(Path(folder), job.model_copy(update={"status": SignalMapStatus.RUNNING}))
    try:
        summary = build_signal_maps(files, folder, ctx, modalities)
    except Exception as error:  # the build's own errors say what was missing; keep the message
        _write_record(Path(folder), _ended(job, error=error))
        raise
    _write_record(Path(folder), _ended(job, summary))
    return summary


def _write_record(folder: Path, job: SignalMapJob) -> None:
    """Replace the job's record at once (readers never see half of one)."""
    folder.mkdir(parents=True, exist_ok=True)
    tmp = folder / (RECORD + ".tmp")
    tmp.write_text(job.model_dump_json(indent=2))
    tmp.replace(folder / RECORD)


def _ended(
    job: SignalMapJob, summary: dict[str, Any] | None = None, error: Exception | None = None
) -> SignalMapJob:
    """The job done with the build's summary, or failed with its error's message."""
    now = datetime.now(UTC)
    if error is not None:
        failed = {
            "status": SignalMapStatus.FAILED,
            "finished_at": now,
            "error": str(error) or type(error).__name__,
        }
        return job.model_copy(update=failed)
    return job.model_copy(update={"status": SignalMapStatus.DONE, "finished_at": now, **(summary or {})})
