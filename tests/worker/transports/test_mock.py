"""The mock transport passes the conformance suite (its storage is a local folder)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from tests.worker.transports.contract import *  # noqa: F403
from tests.worker.transports.contract import get, put
from worker.transports.base import NotFound, Permanent, PermissionDenied
from worker.transports.mock import MockOptions, MockTransport, machine_folder


@pytest.fixture
def transport(tmp_path: Path) -> Iterator[MockTransport]:
    mock = MockTransport(MockOptions(), folder=tmp_path / "machine")
    yield mock
    mock.close()


# -- the state every opener of a machine shares ------------------------------------


def _list_at_once(openers: list[MockTransport]) -> None:
    with ThreadPoolExecutor(len(openers)) as pool:
        list(pool.map(lambda mock: mock.list_dir(""), openers))


def test_operations_are_counted_across_openers_threads_and_processes(tmp_path: Path) -> None:
    folder = tmp_path / "machine"
    slow = MockOptions(latency_ms=1000)  # two threads started apart on a busy host still meet
    one, two = MockTransport(slow, folder=folder), MockTransport(slow, folder=folder)

    _list_at_once([one, one])  # one opener, two threads
    assert one.peak_active() == 2
    one.reset_peak()
    _list_at_once([one, two])  # two openers in one process
    assert two.peak_active() == 2
    one.reset_peak()
    other = subprocess.Popen([sys.executable, "-c", (
        "import sys; from pathlib import Path; "
        "from worker.transports.mock import MockOptions, MockTransport; "
        "MockTransport(MockOptions(latency_ms=1500), folder=Path(sys.argv[1])).list_dir('')"),
        str(folder)])
    try:
        deadline = time.monotonic() + 10
        while one.peak_active() < 1 and time.monotonic() < deadline:
            time.sleep(0.02)  # the other process's operation has begun
        _list_at_once([one])
    finally:
        assert other.wait(10) == 0
    assert one.peak_active() == 2
    one.close()
    two.close()


def test_a_machine_folder_made_again_starts_its_counters_afresh(tmp_path: Path) -> None:
    folder = tmp_path / "machine"
    first = MockTransport(MockOptions(latency_ms=50), folder=folder)
    _list_at_once([first, first])
    first.close()
    shutil.rmtree(folder)

    again = MockTransport(MockOptions(), folder=folder)
    again.list_dir("")

    assert again.peak_active() == 1
    assert (folder / "counters").exists()
    again.close()


# -- what is planted in its storage: links, pipes ------------------------------------------


@pytest.fixture
def outside(tmp_path: Path) -> Path:
    """A folder beside the machine's, with a file a link might reach."""
    folder = tmp_path / "outside"
    folder.mkdir()
    (folder / "secret.txt").write_text("not the machine's")
    return folder


def test_a_link_out_of_the_storage_is_not_listed(transport: MockTransport, outside: Path) -> None:
    (transport.files / "to_file.nc").symlink_to(outside / "secret.txt")
    (transport.files / "to_folder").symlink_to(outside)

    assert transport.list_dir("") == []


@pytest.mark.parametrize("path", ["to_file.nc", "to_folder/secret.txt"])
def test_a_link_out_of_the_storage_is_not_read(
        transport: MockTransport, outside: Path, path: str) -> None:
    (transport.files / "to_file.nc").symlink_to(outside / "secret.txt")
    (transport.files / "to_folder").symlink_to(outside)

    with pytest.raises(PermissionDenied):
        b"".join(transport.read(path))
    with pytest.raises(PermissionDenied):
        transport.stat(path)


def test_a_link_out_of_the_storage_is_not_written_through(
        transport: MockTransport, outside: Path) -> None:
    (transport.files / "to_folder").symlink_to(outside)

    with pytest.raises(PermissionDenied):
        transport.write("to_folder/new.nc", [b"G0\n"])
    with pytest.raises(PermissionDenied):
        transport.make_dir("to_folder/sub")
    assert sorted(p.name for p in outside.iterdir()) == ["secret.txt"]


def test_a_link_out_of_the_storage_is_not_deleted_through(
        transport: MockTransport, outside: Path) -> None:
    (transport.files / "to_file.nc").symlink_to(outside / "secret.txt")
    (transport.files / "to_folder").symlink_to(outside)

    for delete in (lambda: transport.delete("to_file.nc"),
                   lambda: transport.delete("to_folder/secret.txt")):
        with pytest.raises(PermissionDenied):
            delete()
    assert (outside / "secret.txt").read_text() == "not the machine's"


def test_a_link_out_of_the_storage_deep_in_its_folders_is_not_reached(
        transport: MockTransport, outside: Path) -> None:
    (transport.files / "a" / "b").mkdir(parents=True)
    (transport.files / "a" / "b" / "to_folder").symlink_to(outside)

    for refused in (lambda: transport.stat("a/b/to_folder/secret.txt"),
                    lambda: b"".join(transport.read("a/b/to_folder/secret.txt")),
                    lambda: transport.write("a/b/to_folder/new.nc", [b"G0\n"]),
                    lambda: transport.delete("a/b/to_folder/secret.txt")):
        with pytest.raises(PermissionDenied):
            refused()
    assert sorted(p.name for p in outside.iterdir()) == ["secret.txt"]


def test_a_folder_reached_through_a_link_is_still_confined(
        tmp_path: Path, outside: Path) -> None:
    from worker.transports.mounted_folder import MountedFolder

    real = tmp_path / "share"
    (real / "sub").mkdir(parents=True)
    (real / "sub" / "P1.nc").write_bytes(b"G0\n")
    (real / "sub" / "to_folder").symlink_to(outside)
    (tmp_path / "mounted").symlink_to(real)
    disk = MountedFolder(str(tmp_path / "mounted"))  # its path is not its real path

    assert [e.name for e in disk.list("sub")] == ["P1.nc"]
    assert disk.stat("sub/P1.nc").size == 3
    with pytest.raises(PermissionError):
        disk.stat("sub/to_folder/secret.txt")


def test_a_link_inside_the_storage_is_followed(transport: MockTransport) -> None:
    put(transport, "real.nc", b"G0 X1\n")
    (transport.files / "alias.nc").symlink_to(transport.files / "real.nc")

    assert [e.name for e in transport.list_dir("")] == ["alias.nc", "real.nc"]
    assert get(transport, "alias.nc") == b"G0 X1\n"


@pytest.mark.timeout(20)  # a pipe that blocked would hang here, not fail an assert
def test_a_named_pipe_is_neither_listed_nor_read_and_the_machine_keeps_answering(
        transport: MockTransport) -> None:
    os.mkfifo(transport.files / "pipe.nc")
    put(transport, "P1.nc", b"G0\n")

    assert [e.name for e in transport.list_dir("")] == ["P1.nc"]
    for refused in (lambda: b"".join(transport.read("pipe.nc")),
                    lambda: transport.stat("pipe.nc"), lambda: transport.delete("pipe.nc")):
        with pytest.raises(NotFound):
            refused()
    assert get(transport, "P1.nc") == b"G0\n"


# -- where its state lives, and what options.json may say ---------------------------------


def test_a_machine_folder_that_links_into_another_machines_storage_is_refused(
        tmp_path: Path) -> None:
    area = tmp_path / "mock"
    (area / "m2" / "files").mkdir(parents=True)
    (area / "m1").symlink_to(area / "m2" / "files")

    with pytest.raises(PermissionDenied, match="link out of data/mock/"):
        machine_folder(area, "m1")


def test_a_machine_folder_that_links_out_of_the_mock_area_is_refused(tmp_path: Path) -> None:
    area = tmp_path / "mock"
    area.mkdir()
    (area / "m1").symlink_to(tmp_path)

    with pytest.raises(PermissionDenied):
        machine_folder(area, "m1")


@pytest.mark.parametrize(("written", "said"), [
    ('{"latency_ms": -5}', "options.json of this mock machine is not valid: latency_ms: "),
    ('{"folder": "m2"}', "options.json of this mock machine cannot set folder"),
    ('{"nonsense": 1}', "options.json of this mock machine cannot set nonsense"),
    ('{"offline": tru', "options.json of this mock machine is not JSON"),
    ("[1, 2]", "options.json of this mock machine holds no JSON object"),
])
def test_a_bad_options_json_is_refused_with_what_is_wrong(
        transport: MockTransport, written: str, said: str) -> None:
    (transport.folder / "options.json").write_text(written)

    with pytest.raises(Permanent) as refused:
        transport.list_dir("")
    assert str(refused.value).startswith(said)


def test_a_mock_tells_the_free_space_of_the_disk_its_storage_is_on(
        transport: MockTransport, tmp_path: Path) -> None:
    told = transport.free_bytes()

    assert told is not None
    assert abs(told - shutil.disk_usage(tmp_path).free) < 256 * 1024**2
