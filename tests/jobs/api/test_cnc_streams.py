"""Large files: the stream endpoints move any size in bounded memory; receiveFile stops at 10 MB.

The round trips run against a real server on loopback: the test client would read
a streamed request body whole before the app sees it.
"""

from __future__ import annotations

import hashlib
import logging
import os
import random
import tracemalloc
from collections.abc import Iterator

import httpx
import pytest

from jobs.api.app import create_app
from tests.conftest import API_KEY
from tests.live_server import serving

MiB = 1024 * 1024
FILE_BYTES = 50 * MiB
CHUNK_BYTES = 256 * 1024
MAX_TRACED_PEAK_BYTES = 20 * MiB  # well below the file: nothing may hold it whole
RECEIVE_FILE_LIMIT_BYTES = 10 * MiB  # the contract's limit of receiveFile (JSON)
PARAMS = {"machineID": "sim", "fileName": "BIG.NC"}


@pytest.fixture
def sim(add_machines) -> None:
    add_machines({"id": "sim", "name": "Sim", "model": "Mock"})


@pytest.fixture
def http(settings, sim) -> Iterator[httpx.Client]:
    """A client of the API served for real on loopback."""
    with serving(create_app(settings)) as live, httpx.Client(
            base_url=live.url, headers={"X-Api-Key": API_KEY}, timeout=120) as client:
        yield client


def generated(digest: hashlib._Hash) -> Iterator[bytes]:
    """FILE_BYTES of pseudo-random bytes, chunk by chunk, fed to `digest` on the way."""
    rng = random.Random(7)
    for _ in range(FILE_BYTES // CHUNK_BYTES):
        chunk = rng.randbytes(CHUNK_BYTES)
        digest.update(chunk)
        yield chunk


def round_trip(http: httpx.Client) -> tuple[str, str, int]:
    """Send FILE_BYTES through sendFileStream, read them back: (sent sha256, received, size)."""
    sent = hashlib.sha256()
    answer = http.post("/api/cnc/sendFileStream", params=PARAMS, content=generated(sent))
    assert answer.json() == {"errorCode": 0, "errorMsg": "Success"}
    received, size = hashlib.sha256(), 0
    with http.stream("GET", "/api/cnc/receiveFileStream", params=PARAMS) as response:
        assert response.headers["content-type"] == "application/octet-stream"
        for chunk in response.iter_bytes():
            received.update(chunk)
            size += len(chunk)
    return sent.hexdigest(), received.hexdigest(), size


def test_50_mb_file_comes_back_from_receive_file_stream_byte_identical(http, settings):
    sent, received, size = round_trip(http)

    assert size == FILE_BYTES
    assert received == sent
    assert (settings.data_dir / "mock" / "sim" / "files" / "BIG.NC").stat().st_size == FILE_BYTES


def test_50_mb_stream_round_trip_keeps_memory_well_below_the_file_size(http):
    # The server runs in a thread of this process, so tracemalloc sees both ends.
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        round_trip(http)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()

    assert peak < MAX_TRACED_PEAK_BYTES


def test_receive_file_refuses_a_file_over_10_mb_with_20012(client, sim):
    client.post("/api/cnc/sendFileStream", params=PARAMS,
                content=b"x" * (RECEIVE_FILE_LIMIT_BYTES + 1))

    body = client.get("/api/cnc/receiveFile", params=PARAMS).json()

    assert body["errorCode"] == 20012
    assert body["errorMsg"] == "File is too large for this endpoint."
    assert "receiveFileStream" in body["statusMsg"]


def test_receive_file_answers_a_file_of_exactly_10_mb(client, sim):
    client.post("/api/cnc/sendFileStream", params=PARAMS,
                content=b"x" * RECEIVE_FILE_LIMIT_BYTES)

    body = client.get("/api/cnc/receiveFile", params=PARAMS).json()

    assert len(body["content"]) == RECEIVE_FILE_LIMIT_BYTES


def test_a_client_that_stops_reading_a_download_does_not_hold_the_machine(settings, sim):
    settings = settings.model_copy(update={"busy_wait_s": 2.0})
    big = settings.data_dir / "mock" / "sim" / "files" / "BIG.NC"
    big.parent.mkdir(parents=True, exist_ok=True)
    big.write_bytes(random.Random(3).randbytes(20 * MiB))  # far more than socket buffers
    with serving(create_app(settings)) as live, httpx.Client(
            base_url=live.url, headers={"X-Api-Key": API_KEY}, timeout=30) as http:
        with http.stream("GET", "/api/cnc/receiveFileStream", params=PARAMS) as stalled:
            received = stalled.iter_bytes()  # kept: a dropped iterator closes the stream
            next(received)  # the client takes one chunk, then stops reading

            listing = http.get("/api/cnc/readProgramList", params={"machineID": "sim"})

            assert listing.json().get("errorCode", 0) == 0, listing.json()  # not 20007 busy
            assert "BIG.NC" in listing.json()["programs"]


def test_a_machine_failing_mid_download_cuts_the_response_short_and_frees_it(
        settings, sim, monkeypatch, caplog):
    from worker.transports.base import Dropped
    from worker.transports.mock import MockTransport

    big = settings.data_dir / "mock" / "sim" / "files" / "BIG.NC"
    big.parent.mkdir(parents=True, exist_ok=True)
    big.write_bytes(b"G1 X1\n" * MiB)
    read = MockTransport.read

    def dropping(self: MockTransport, path: str, **kwargs: object) -> Iterator[bytes]:
        chunks = read(self, path, **kwargs)
        yield next(chunks)
        raise Dropped("link lost mid-file")

    monkeypatch.setattr(MockTransport, "read", dropping)
    with serving(create_app(settings)) as live, httpx.Client(
            base_url=live.url, headers={"X-Api-Key": API_KEY}, timeout=30) as http:
        server_log = logging.getLogger("uvicorn.error")  # uvicorn's, which does not propagate
        monkeypatch.setattr(server_log, "handlers", [*server_log.handlers, caplog.handler])
        with pytest.raises(httpx.RemoteProtocolError), \
                http.stream("GET", "/api/cnc/receiveFileStream", params=PARAMS) as response:
            assert response.headers["content-length"] == str(6 * MiB)
            b"".join(response.iter_bytes())  # never a whole-looking file
        listing = http.get("/api/cnc/readProgramList", params={"machineID": "sim"})
    assert listing.json()["programs"] == ["BIG.NC"]  # the machine's slot was given back
    # Logged once, as one line that names the file and the machine; no traceback anywhere.
    said = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert [r.getMessage() for r in said] == [
        "download of BIG.NC from machine sim broke off; the client got an incomplete "
        "download: 20006 Connection to the machine failed. link lost mid-file"]
    assert not any(r.exc_info for r in caplog.records)


@pytest.mark.parametrize("said", [-3, 3], ids=["file-shorter", "file-longer"])
def test_a_file_whose_size_the_machine_got_wrong_never_downloads_whole(
        settings, sim, monkeypatch, said):
    from dataclasses import replace

    from worker.transports.mock import MockTransport

    data = b"G1 X1\n" * 100_000
    big = settings.data_dir / "mock" / "sim" / "files" / "BIG.NC"
    big.parent.mkdir(parents=True, exist_ok=True)
    big.write_bytes(data)
    stat = MockTransport.stat
    monkeypatch.setattr(MockTransport, "stat", lambda self, path: replace(
        stat(self, path), size=len(data) - said))  # a server whose SIZE is wrong

    with serving(create_app(settings)) as live, httpx.Client(
            base_url=live.url, headers={"X-Api-Key": API_KEY}, timeout=30) as http:
        with pytest.raises(httpx.RemoteProtocolError), \
                http.stream("GET", "/api/cnc/receiveFileStream", params=PARAMS) as response:
            assert response.headers["content-length"] == str(len(data) - said)
            b"".join(response.iter_bytes())  # incomplete, never a whole-looking wrong file
        listing = http.get("/api/cnc/readProgramList", params={"machineID": "sim"})
    assert listing.json()["programs"] == ["BIG.NC"]  # the machine's slot was given back


def test_a_file_of_its_stated_size_downloads_whole_even_when_empty(settings, sim, http) -> None:
    folder = settings.data_dir / "mock" / "sim" / "files"
    folder.mkdir(parents=True, exist_ok=True)
    for name, data in (("EMPTY.NC", b""), ("ONE.NC", b"%"), ("BIG.NC", b"G0\n" * 300_000)):
        (folder / name).write_bytes(data)
        got = http.get("/api/cnc/receiveFileStream", params={"machineID": "sim", "fileName": name})
        assert got.content == data


def test_the_last_byte_waits_until_the_file_is_known_to_end_at_its_size() -> None:
    from jobs.api.routes.cnc import _exactly
    from jobs.errors import ContractError

    def sent(chunks: list[bytes], size: int) -> tuple[bytes, bool]:
        out, stream = b"", _exactly(iter(chunks), size, "P.NC")
        try:
            for chunk in stream:
                out += chunk
        except ContractError:
            return out, False
        return out, True

    assert sent([b"abc", b"def"], 6) == (b"abcdef", True)
    assert sent([b"abc", b"", b"def", b""], 6) == (b"abcdef", True)
    assert sent([], 0) == (b"", True)
    # The file goes on past its size at a chunk's edge: cut one byte short of the size.
    assert sent([b"abc", b"def"], 3) == (b"ab", False)
    assert sent([b"abc"], 5) == (b"abc", False)  # shorter than its size: short, and an error


def test_a_name_that_is_not_text_is_left_out_of_listings_not_a_500(
        client, add_machines, tmp_path) -> None:
    folder = tmp_path / "share"
    (folder / "sub").mkdir(parents=True)
    (folder / "A.nc").write_bytes(b"A")
    for where in (folder, folder / "sub"):
        with open(os.path.join(os.fsencode(where), b"bad\xffname.nc"), "wb") as f:
            f.write(b"B")
    add_machines({"id": "s1", "name": "Share", "model": "Shared folder", "transport": "share",
                  "options": {"path": str(folder)}})

    listing = client.get("/api/cnc/readProgramList", params={"machineID": "s1"})
    everything = client.get("/api/cnc/readAllPrograms", params={"machineID": "s1"})

    assert listing.status_code == 200 and listing.json()["programs"] == ["A.nc"]
    assert everything.status_code == 200
    assert [p["fileName"] for p in everything.json()["programs"]] == ["A.nc"]
