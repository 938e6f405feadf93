"""Public data sets a user fetches: ``crowdslam datasets fetch msindoor20``.

The Indoor Location Competition 2.0 sample (MIT licence) lives in its GitHub repository. The project ships a
manifest of the files it measures on (``server/data/msindoor20.json``: each file's path, size and SHA-256);
the fetch downloads exactly those, checks each against it, and keeps a file only once it checks. A file
already present and whole is not downloaded again, so an interrupted fetch resumes.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import httpx

MSINDOOR20 = "msindoor20"
UPSTREAM = "https://raw.githubusercontent.com/location-competition/indoor-location-competition-20/master/"
"""The repository's files, served raw; the data set's ``site1/F1/x`` is ``data/site1/F1/x`` there."""


class FetchError(Exception):
    """The fetch cannot go on (an unknown floor, a file that does not check, the source unreachable);
    the message says what and what to do."""


@dataclass(frozen=True)
class ManifestFile:
    path: str
    """Within the data set: ``site1/F1/path_data_files/<walk>.txt``, ``LICENSE``."""
    size: int
    sha256: str


@dataclass(frozen=True)
class Manifest:
    files: tuple[ManifestFile, ...]

    @property
    def floors(self) -> list[str]:
        """``site1/F1``, ``site2/F2``, ...: the floors the manifest holds."""
        return sorted({"/".join(f.path.split("/")[:2]) for f in self.files if f.path.count("/") >= 2})

    def select(self, floors: Sequence[str] | None) -> list[ManifestFile]:
        """The files of these floors (all when None), with the licence."""
        if floors is None:
            return list(self.files)
        unknown = sorted(set(floors) - set(self.floors))
        if unknown:
            raise FetchError(
                f"{MSINDOOR20} has no floor {', '.join(unknown)}; its floors: {', '.join(self.floors)}"
            )
        wanted = tuple(f"{floor}/" for floor in floors)
        return [f for f in self.files if f.path.startswith(wanted) or "/" not in f.path]


def load_manifest(path: Path | None = None) -> Manifest:
    """The shipped manifest (``server/data/msindoor20.json``), or the one at ``path``."""
    text = (
        path.read_text()
        if path
        else resources.files("server.data").joinpath(f"{MSINDOOR20}.json").read_text()
    )
    raw = json.loads(text)
    return Manifest(
        tuple(ManifestFile(path, int(e["size"]), str(e["sha256"])) for path, e in raw["files"].items())
    )


def write_manifest(root: Path, out: Path) -> int:
    """The manifest of a copy of the data set at ``root`` (its floors' files and ``LICENSE``); returns the
    number of files. How ``server/data/msindoor20.json`` was made from the copy the project measures on."""
    paths = [root / "LICENSE", *sorted(p for p in root.glob("site*/*/**/*") if p.is_file())]
    files = {p.relative_to(root).as_posix(): {"size": p.stat().st_size, "sha256": _sha256(p)} for p in paths}
    out.write_text(
        json.dumps({"dataset": MSINDOOR20, "source": UPSTREAM, "licence": "MIT", "files": files}, indent=1)
        + "\n"
    )
    return len(files)


def dataset_dir(data_dir: Path) -> Path:
    """Where the fetch puts the data set: ``<data dir>/datasets/msindoor20``."""
    return data_dir / "datasets" / MSINDOOR20


@dataclass(frozen=True)
class Fetched:
    root: Path
    downloaded: int
    already_there: int
    bytes_downloaded: int


def fetch(
    root: Path,
    files: Iterable[ManifestFile],
    source: str = UPSTREAM,
    progress: Callable[[int], None] = lambda n: None,
    client: httpx.Client | None = None,
) -> Fetched:
    """Download ``files`` from ``source`` into ``root``, each checked against its size and SHA-256 before it
    takes its place (written to ``<name>.part`` first). ``progress`` is called with the bytes of each file
    as it is done."""
    downloaded = present = total = 0
    own = client is None
    http = client or httpx.Client(timeout=httpx.Timeout(60.0, connect=15.0), follow_redirects=True)
    try:
        for entry in files:
            target = root / entry.path
            if target.is_file() and target.stat().st_size == entry.size and _sha256(target) == entry.sha256:
                present += 1
                progress(entry.size)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            total += _download(http, source.rstrip("/") + "/" + _upstream_path(entry.path), entry, target)
            downloaded += 1
            progress(entry.size)
    finally:
        if own:
            http.close()
    return Fetched(root, downloaded, present, total)


def _upstream_path(path: str) -> str:
    return path if "/" not in path else f"data/{path}"


def _download(http: httpx.Client, url: str, entry: ManifestFile, target: Path) -> int:
    part = target.with_name(target.name + ".part")
    digest = hashlib.sha256()
    size = 0
    try:
        with http.stream("GET", url) as response:
            if response.status_code != 200:
                raise FetchError(f"{url}: the source answered {response.status_code}")
            with part.open("wb") as sink:
                for chunk in response.iter_bytes(1 << 16):
                    size += len(chunk)
                    if size > entry.size:
                        raise FetchError(f"{url}: more than the {entry.size} bytes expected; not kept")
                    digest.update(chunk)
                    sink.write(chunk)
        if size != entry.size or digest.hexdigest() != entry.sha256:
            raise FetchError(
                f"{url}: {size} bytes with SHA-256 {digest.hexdigest()[:16]}..., expected {entry.size} bytes "
                f"with {entry.sha256[:16]}...; not kept (has the repository changed? try --ref)"
            )
        os.replace(part, target)
    except httpx.HTTPError as exc:
        raise FetchError(f"cannot download {url}: {exc}") from None
    finally:
        part.unlink(missing_ok=True)
    return size


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as source:
        for chunk in iter(lambda: source.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def as_source(ref: str) -> str:
    """The raw-file address of the repository at a branch, tag or commit."""
    return UPSTREAM.replace("/master/", f"/{ref}/")


def manifest_summary(files: Sequence[ManifestFile]) -> dict[str, Any]:
    return {"files": len(files), "bytes": sum(f.size for f in files)}
