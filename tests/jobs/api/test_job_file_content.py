"""`POST /api/jobs` of a send whose file cannot be read from the body."""

from __future__ import annotations

import pytest


@pytest.mark.parametrize(("file", "said"), [
    ({"base64": "@@"}, "base64 is not valid Base64"),
    ({"content": "x", "encoding": "nope"}, "unknown encoding 'nope'"),
    ({"content": "é", "encoding": "us-ascii"}, "content cannot be written in us-ascii"),
])
@pytest.mark.parametrize("dry_run", [False, True])
def test_a_send_whose_file_cannot_be_read_is_refused_with_400_and_nothing_queued(
        client, add_machines, file, said, dry_run) -> None:
    add_machines({"id": "1010", "name": "A", "model": "Mock"})

    response = client.post("/api/jobs", json={"kind": "send", "fileName": "P.nc", **file,
                                              "machines": {"ids": ["1010"]},
                                              "dry_run": dry_run})

    assert response.status_code == 400  # not a 200 a client would take for a job made
    assert response.json()["errorCode"] == 20001
    assert response.json()["statusMsg"] == said
    assert client.get("/api/jobs").json() == []
