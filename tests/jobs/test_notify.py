"""jobs.notify against a real HTTP server on loopback that records what it receives."""

from __future__ import annotations

import base64
import logging
import sys
from collections.abc import Callable

import pytest

from jobs.notify import notify
from tests.jobs.recording_server import RecordingServer
from tests.servers import free_port


def test_webhook_receives_title_body_and_details_as_json(
        webhook_server: Callable[..., RecordingServer]) -> None:
    server = webhook_server()

    failures = notify(urls=[server.url()], title="Backup failed", body="3 of 40 machines failed",
                      details={"job_id": "j-42", "machines": ["mill-1", "lathe-7"]})

    assert failures == []
    [request] = server.requests
    assert request.path == "/hook"
    assert request.headers["Content-Type"] == "application/json"
    assert request.json() == {"title": "Backup failed", "body": "3 of 40 machines failed",
                              "details": {"job_id": "j-42", "machines": ["mill-1", "lathe-7"]}}


def test_webhook_without_details_gets_an_empty_details_object(
        webhook_server: Callable[..., RecordingServer]) -> None:
    server = webhook_server()

    assert notify(urls=[server.url()], title="t", body="b") == []
    assert server.requests[0].json() == {"title": "t", "body": "b", "details": {}}


def test_webhook_sends_userinfo_as_basic_auth_and_keeps_the_query_without_logging_them(
        webhook_server: Callable[..., RecordingServer], caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    server = webhook_server()

    failures = notify(urls=[f"http://user:s3cret@127.0.0.1:{server.port}/hook?token=zq-tok"],
                      title="t", body="b")

    assert failures == []
    [request] = server.requests
    assert request.path == "/hook?token=zq-tok"
    assert request.headers["Authorization"] == "Basic " + base64.b64encode(
        b"user:s3cret").decode()
    assert "s3cret" not in caplog.text
    assert "zq-tok" not in caplog.text


def test_unreachable_webhook_is_reported_as_a_failure_without_raising() -> None:
    closed_port = free_port()

    failures = notify(urls=[f"http://127.0.0.1:{closed_port}/hook"], title="t", body="b",
                      timeout_s=5.0)

    assert len(failures) == 1
    assert failures[0].startswith(f"urls[0] http://127.0.0.1:{closed_port}/***: ConnectError")


def test_webhook_answering_an_error_status_is_a_failure(
        webhook_server: Callable[..., RecordingServer]) -> None:
    server = webhook_server(status=500)

    failures = notify(urls=[server.url()], title="t", body="b")

    assert failures == [f"urls[0] {server.url('/***')}: HTTP 500 Internal Server Error"]


def test_password_path_and_query_never_appear_in_failures_or_logs(
        webhook_server: Callable[..., RecordingServer], caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    server = webhook_server()  # speaks plain HTTP, so the https handshake fails
    # Slack's and Discord's webhooks carry their token in the path
    url = f"https://user:s3cret@127.0.0.1:{server.port}/services/T0K3NPATH?token=zq-tok"

    failures = notify(urls=[url], title="t", body="b", timeout_s=5.0)

    assert len(failures) == 1
    assert failures[0].startswith(f"urls[0] https://***@127.0.0.1:{server.port}/***?***: ")
    for secret in ("s3cret", "zq-tok", "T0K3NPATH"):
        assert secret not in failures[0]
        assert secret not in caplog.text
    assert "urls[0] https://***@127.0.0.1" in caplog.text  # the failure is logged, redacted


def test_one_failing_url_does_not_stop_the_others(
        webhook_server: Callable[..., RecordingServer]) -> None:
    good = webhook_server()
    closed_port = free_port()

    failures = notify(urls=[f"http://127.0.0.1:{closed_port}/", good.url()], title="t", body="b",
                      timeout_s=5.0)

    assert [f.partition(" ")[0] for f in failures] == ["urls[0]"]
    assert len(good.requests) == 1


def test_no_urls_is_no_failure() -> None:
    assert notify(urls=[], title="t", body="b") == []


def test_a_url_without_a_scheme_is_reported() -> None:
    failures = notify(urls=["127.0.0.1:8080/hook"], title="t", body="b")

    assert failures == ["urls[0] ://…: not a URL (no scheme such as https:// or mailto://)"]


def test_other_schemes_without_apprise_say_apprise_is_not_installed(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "apprise", None)  # makes `import apprise` fail

    failures = notify(urls=["tgram://bottoken/chat-id"], title="t", body="b")

    assert failures == ["urls[0] tgram://…: the tgram:// scheme needs the apprise library "
                        "(the notify extra); only http:// and https:// webhooks work "
                        "without it"]
    assert "bottoken" not in failures[0]


def test_apprise_json_scheme_posts_to_the_loopback_server(
        webhook_server: Callable[..., RecordingServer]) -> None:
    pytest.importorskip("apprise")
    server = webhook_server(status=200)

    failures = notify(urls=[f"json://127.0.0.1:{server.port}/apprise"], title="Backup failed",
                      body="mill-1 timed out", details={"job_id": "j-42"})

    assert failures == []
    [request] = server.requests
    assert request.path == "/apprise"
    payload = request.json()
    assert isinstance(payload, dict)
    assert payload["title"] == "Backup failed"
    assert payload["message"] == "mill-1 timed out\n\njob_id: j-42"


def test_apprise_failure_hides_the_password_and_query(
        caplog: pytest.LogCaptureFixture) -> None:
    pytest.importorskip("apprise")
    caplog.set_level(logging.DEBUG)
    closed_port = free_port()

    failures = notify(urls=[f"json://user:s3cret@127.0.0.1:{closed_port}/hook?token=zq-tok"],
                      title="t", body="b", timeout_s=5.0)

    assert len(failures) == 1
    assert "apprise could not deliver it" in failures[0]
    for secret in ("s3cret", "zq-tok"):
        assert secret not in failures[0]
        assert secret not in caplog.text


@pytest.mark.parametrize("delivered", [True, False])
def test_an_apprise_urls_token_in_its_path_is_kept_out_of_failures_and_debug_logs(
        webhook_server: Callable[..., RecordingServer], caplog: pytest.LogCaptureFixture,
        delivered: bool) -> None:
    pytest.importorskip("apprise")
    caplog.set_level(logging.DEBUG)
    port = webhook_server(status=200).port if delivered else free_port()

    failures = notify(urls=[f"json://127.0.0.1:{port}/hooks/zq-path-tok3n"], title="t",
                      body="b", timeout_s=5.0)

    assert failures == ([] if delivered else [
        f"urls[0] json://127.0.0.1:{port}/***?***: apprise could not deliver it "
        "(its log says why)"])
    assert "zq-path-tok3n" not in caplog.text
    assert f"127.0.0.1:{port}" in caplog.text  # where it went is still said


def test_a_scheme_apprise_does_not_know_is_reported_without_the_url(
        caplog: pytest.LogCaptureFixture) -> None:
    pytest.importorskip("apprise")
    caplog.set_level(logging.DEBUG)

    failures = notify(urls=["nosuchservice://user:s3cret@host/x?token=zq-tok"], title="t", body="b")

    assert failures == ["urls[0] nosuchservice://…: apprise does not know the "
                        "nosuchservice:// scheme"]
    assert "s3cret" not in caplog.text


def test_a_url_that_can_never_receive_an_alert_is_told_apart_without_its_secrets():
    from jobs.notify import problem_with

    assert problem_with("https://user:secret@hooks.example/x") is None
    assert problem_with("mailto://user:secret@example.com") is None
    assert problem_with("not a url") == "not a URL (no scheme such as https:// or mailto://)"
    assert problem_with("file:///etc/passwd") == "apprise does not know the file:// scheme"
    assert "secret" not in str(problem_with("https://user:secret@/x"))
