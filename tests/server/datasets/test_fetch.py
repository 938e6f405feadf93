"""``crowdslam datasets fetch``: the public walks downloaded from a mirror served here (the repository's own
sample, laid out as the data set's GitHub repository), each file checked before it takes its place."""

from __future__ import annotations

import functools
import http.server
import json
import shutil
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from server.cli.main import main
from server.datasets import fetch as fetching
from server.datasets.fetch import FetchError, Manifest, dataset_dir, fetch, load_manifest, write_manifest
from tests.conftest import SAMPLE_WALKS, public_walks

pytestmark = pytest.mark.walks


@pytest.fixture
def mirror(tmp_path: Path) -> Iterator[tuple[str, Path, Manifest]]:
    """The sample as the repository serves it (``data/site1/F1/...``, ``LICENSE``), and its manifest."""
    root = tmp_path / "mirror"
    shutil.copytree(SAMPLE_WALKS / "site1", root / "data" / "site1")
    shutil.copy(SAMPLE_WALKS / "LICENSE", root / "LICENSE")
    manifest_file = tmp_path / "manifest.json"
    assert write_manifest(SAMPLE_WALKS, manifest_file) == 1 + 3 + 8  # licence, plan files, walks
    handler = functools.partial(QuietHandler, directory=str(root))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/", root, load_manifest(manifest_file)
    finally:
        server.shutdown()
        server.server_close()


class QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format: str, *args: object) -> None:
        return


def _tree(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_a_fetch_gets_every_file_checked_and_a_second_one_nothing(
    mirror: tuple[str, Path, Manifest], tmp_path: Path
) -> None:
    source, _, manifest = mirror
    target = tmp_path / "data" / "datasets" / "msindoor20"
    done: list[int] = []
    first = fetch(target, manifest.select(["site1/F1"]), source, progress=done.append)
    assert (first.downloaded, first.already_there) == (12, 0)
    assert first.bytes_downloaded == sum(done) == sum(f.size for f in manifest.files)
    expected = {k: v for k, v in _tree(SAMPLE_WALKS).items() if k != "README.md"}
    assert _tree(target) == expected
    again = fetch(target, manifest.files, source)
    assert (again.downloaded, again.already_there, again.bytes_downloaded) == (0, 12, 0)


def test_a_file_that_does_not_check_is_not_kept(mirror: tuple[str, Path, Manifest], tmp_path: Path) -> None:
    source, root, manifest = mirror
    walk = next((root / "data" / "site1" / "F1" / "path_data_files").glob("*.txt"))
    walk.write_bytes(walk.read_bytes().replace(b"TYPE_WAYPOINT", b"TYPE_WAYPOINX", 1))  # same size
    target = tmp_path / "fetched"
    with pytest.raises(FetchError, match=rf"{walk.name}: .* not kept"):
        fetch(target, manifest.files, source)
    assert not (target / "site1" / "F1" / "path_data_files" / walk.name).exists()
    assert not list(target.rglob("*.part"))
    walk.write_bytes(walk.read_bytes() + b"\n")  # one byte too many
    with pytest.raises(FetchError, match="more than the"):
        fetch(target, manifest.files, source)
    with pytest.raises(FetchError, match="answered 404"):
        fetch(target, manifest.files, source + "elsewhere/")
    with pytest.raises(FetchError, match="cannot download"):
        fetch(target, manifest.files, "http://127.0.0.1:9/")
    with pytest.raises(FetchError, match="no floor site1/F9; its floors: site1/F1"):
        manifest.select(["site1/F9"])


def test_the_command_fetches_into_the_data_directory_and_says_where(
    mirror: tuple[str, Path, Manifest],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    source, _, manifest = mirror
    monkeypatch.setattr(fetching, "load_manifest", lambda: manifest)
    data_dir = tmp_path / "data"
    argv = ["datasets", "fetch", "msindoor20", "--floors", "site1/F1", "--source", source]
    assert main([*argv, "--data-dir", str(data_dir)]) == 0
    out = capsys.readouterr().out
    root = dataset_dir(data_dir)
    assert f"12 files (4 MB) in {root}: 12 downloaded, 0 already there" in out
    assert f"crowdslam evaluate --msindoor {root / 'site1' / 'F1'}" in out
    assert len(list((root / "site1" / "F1" / "path_data_files").glob("*.txt"))) == 8


def test_the_shipped_manifest_is_the_copy_the_project_measures_on(tmp_path: Path) -> None:
    root = public_walks()
    shipped = load_manifest()
    if root is None or not all((root / floor).is_dir() for floor in shipped.floors):
        pytest.skip("needs the whole public walks: run `crowdslam datasets fetch msindoor20`")
    write_manifest(root, tmp_path / "here.json")
    assert json.loads((tmp_path / "here.json").read_text())["files"] == {
        f.path: {"size": f.size, "sha256": f.sha256} for f in shipped.files
    }
    assert shipped.floors == [
        "site1/F1",
        "site2/F2",
        "site2/F3",
        "site2/F4",
        "site2/F5",
        "site2/F7",
        "site2/F8",
    ]
