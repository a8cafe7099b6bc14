"""A machine behind a server that answers nonsense: contract errors, never a 500 or a hang.

The server is a real HTTP server on loopback that plays another gateway (the `gateway`
transport), answering each machine id in its own wrong way.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, urlsplit

import pytest

from tests.jobs.helpers import wait_done

ANSWERS = {  # what the remote says to readProgramList, by the remote machine id
    "dots": {"dirAtCNC": "/", "programs": ["A.NC"], "subDirs": [".", "", "/", "sub"]},
    "shape": {"dirAtCNC": "/", "programs": 5, "subDirs": []},
    "huge": {"errorCode": 1e400},
    "deep": {"dirAtCNC": "/", "programs": [], "subDirs": ["deeper"]},  # without end
}
TRICKLED_BYTES = 200
TRICKLE_PAUSE_S = 0.05  # 10 s for a whole answer, far below any read timeout per byte


class _Remote(BaseHTTPRequestHandler):
    def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
        url = urlsplit(self.path)
        query = {k: v[0] for k, v in parse_qs(url.query).items()}
        machine = query.get("machineID", "")
        if machine == "trickle":
            self._trickle(json.dumps(ANSWERS["dots"]).encode().ljust(TRICKLED_BYTES))
            return
        if machine == "html":
            body, kind = b"<html>maintenance</html>", "text/html"
        elif url.path.endswith("/readProgramList"):
            answer = ANSWERS[machine]
            if query.get("dirAtCNC", "/").strip("/"):  # a subfolder
                answer = {"dirAtCNC": query["dirAtCNC"], "programs": ["B.NC"],
                          "subDirs": ["deeper"] if machine == "deep" else []}
            body, kind = json.dumps(answer).encode(), "application/json"
        else:
            body, kind = b'{"errorCode": 158, "errorMsg": "Path not found."}', "application/json"
        self.send_response(200)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def _trickle(self, body: bytes) -> None:
        """A whole answer, a byte at a time: never silent for long, never done soon."""
        self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        try:
            for i in range(len(body)):
                self.wfile.write(body[i:i + 1])
                self.wfile.flush()
                time.sleep(TRICKLE_PAUSE_S)
        except OSError:  # the client gave up: what a deadline is for
            pass

    def log_message(self, *_: object) -> None:
        pass


@pytest.fixture
def remote(add_machines) -> Iterator[None]:
    server = ThreadingHTTPServer(("127.0.0.1", 0), _Remote)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    url = f"http://127.0.0.1:{server.server_address[1]}"
    add_machines(*({"id": name, "name": name, "model": "Gateway file server",
                    "transport": "gateway",
                    "options": {"url": url, "machine_id": name, "api_key": "remote-key",
                                "timeout_s": 5}} for name in (*ANSWERS, "html")),
                 {"id": "trickle", "name": "trickle", "model": "Gateway file server",
                  "transport": "gateway",
                  "options": {"url": url, "machine_id": "trickle", "timeout_s": 5,
                              "transfer_timeout_s": 1}})
    yield
    server.shutdown()


@pytest.mark.parametrize("machine", ["shape", "huge", "html"])
def test_an_answer_that_makes_no_sense_is_20006_not_a_500(client, remote, machine) -> None:
    response = client.get("/api/cnc/readProgramList", params={"machineID": machine})

    assert response.status_code == 200
    assert response.json()["errorCode"] == 20006, response.json()


def test_folders_named_dot_or_slash_are_not_walked_into_for_ever(client, remote) -> None:
    response = client.get("/api/cnc/readAllPrograms", params={"machineID": "dots"})

    assert response.status_code == 200
    # The root's file and the one in `sub`; ".", "" and "/" are skipped.
    assert response.json()["programs"] == [{"dirAtCNC": "/", "fileName": "A.NC"},
                                           {"dirAtCNC": "sub", "fileName": "B.NC"}]


def test_folders_that_nest_without_end_are_20006_not_a_hang(client, remote) -> None:
    response = client.get("/api/cnc/readAllPrograms", params={"machineID": "deep"})

    assert response.json()["errorCode"] == 20006
    assert "deeper than 32 levels" in response.json()["statusMsg"]


def test_a_batch_with_a_nonsense_remote_gives_every_target_its_result(
        queue_client, add_machines, remote) -> None:
    add_machines({"id": "m1", "name": "Mock", "model": "Mock"})
    body = {"content": "%\nG0 X0\nM30\n%\n",
            "targets": [{"machineID": "html", "fileName": "P.NC"},
                        {"machineID": "m1", "fileName": "P.NC"}]}
    job = queue_client.post("/api/jobs", json={"kind": "send", **body, "max_attempts": 1}).json()
    done = wait_done(queue_client, job["id"])
    assert [t["errorCode"] for t in done["targets"]] == [20006, 0]


def test_a_remote_that_trickles_its_answer_is_cut_off_at_the_transfer_deadline(
        client, remote) -> None:
    for _ in range(2):  # the machine is free again after the first
        started = time.monotonic()
        response = client.get("/api/cnc/readProgramList", params={"machineID": "trickle"})

        assert response.json()["errorCode"] == 20005, response.json()
        assert "not complete within 1 s" in response.json()["statusMsg"]
        assert time.monotonic() - started < 5  # not the 10 s the whole answer takes
