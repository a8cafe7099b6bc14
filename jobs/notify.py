"""Send an alert to every configured URL and report, never raise, what failed.

http(s) URLs are webhooks that receive a JSON POST; any other scheme (`mailto://`,
`slack://`, `json://` …) goes to the optional apprise library. Secrets in a URL
(userinfo, path, query string: Slack's and Discord's webhooks keep their token in the path)
never appear in the failures returned or in our logs.
"""

from __future__ import annotations

import base64
import json
import logging
import re
from collections.abc import Sequence
from functools import cache
from typing import Any
from urllib.parse import SplitResult, parse_qsl, unquote, urlsplit, urlunsplit

import httpx

log = logging.getLogger(__name__)

WEBHOOK_SCHEMES = frozenset({"http", "https"})
USER_AGENT = "dncq-notify"
_SCHEME = re.compile(r"\s*([A-Za-z][A-Za-z0-9+.-]*)://")  # RFC 3986 scheme


def notify(*, urls: Sequence[str], title: str, body: str, details: dict[str, Any] | None = None,
           timeout_s: float = 10.0) -> list[str]:
    """Send one alert to each URL; return one message per URL that failed (empty: all sent).

    Each message reads `urls[i] <URL without its secrets>: <why>`.
    """
    failures: list[str] = []
    for index, url in enumerate(urls):
        scheme = _scheme(url)
        # The host and path of an apprise URL are often tokens (tgram://bottoken/chat).
        shown = _redacted(url) if scheme in WEBHOOK_SCHEMES else f"{scheme}://…"
        try:
            if scheme in WEBHOOK_SCHEMES:
                failure = _post_webhook(url, title, body, details, timeout_s)
            else:
                shown, failure = _send_with_apprise(url, shown, title, body, details, timeout_s)
        # An alert is sent when something already went wrong: it must not add a crash.
        except Exception as exc:
            failure = _scrubbed(f"{type(exc).__name__}: {exc}", url)
        if failure is None:
            log.debug("notification sent to urls[%d] %s", index, shown)
            continue
        failures.append(f"urls[{index}] {shown}: {failure}")
        log.warning("notification to urls[%d] %s failed: %s", index, shown, failure)
    return failures


def problem_with(url: str) -> str | None:
    """Why `url` can never receive an alert (said without its secrets), or None.

    Checked when a schedule is saved, so that a typo shows then, not at the first failure.
    """
    scheme = _scheme(url)
    if not scheme:
        return "not a URL (no scheme such as https:// or mailto://)"
    if scheme in WEBHOOK_SCHEMES:
        return None if urlsplit(url.strip()).hostname else f"a {scheme}:// URL needs a host"
    try:
        import apprise  # noqa: F401
    except ImportError:
        return (f"the {scheme}:// scheme needs the apprise library (the notify extra); "
                "only http:// and https:// webhooks work without it")
    if scheme not in _apprise_schemes():
        return f"apprise does not know the {scheme}:// scheme"
    return None


def _post_webhook(url: str, title: str, body: str, details: dict[str, Any] | None,
                  timeout_s: float) -> str | None:
    """POST the alert as JSON; None when the server answered 2xx, else why not."""
    parts = urlsplit(url)
    headers = {"Content-Type": "application/json", "User-Agent": USER_AGENT}
    if parts.username is not None or parts.password is not None:
        userinfo = f"{unquote(parts.username or '')}:{unquote(parts.password or '')}"
        headers["Authorization"] = "Basic " + base64.b64encode(userinfo.encode()).decode("ascii")
    target = urlunsplit(parts._replace(netloc=_host_port(parts)))
    payload = {"title": title, "body": body, "details": details or {}}
    request = httpx.Request(
        "POST", target, headers=headers,
        content=json.dumps(payload, default=str).encode(),  # datetimes, paths … as text
        extensions={"timeout": httpx.Timeout(timeout_s).as_dict()},
    )
    # The transport, not a Client: Client logs every request's full URL, query included.
    try:
        with httpx.HTTPTransport() as transport:
            response = transport.handle_request(request)
            response.close()
    except httpx.HTTPError as exc:
        return _scrubbed(f"{type(exc).__name__}: {exc}", url)
    if not response.is_success:
        return f"HTTP {response.status_code} {response.reason_phrase}".rstrip()
    return None


def _send_with_apprise(url: str, shown: str, title: str, body: str,
                       details: dict[str, Any] | None, timeout_s: float) -> tuple[str, str | None]:
    """Hand the alert to apprise; return the URL as apprise shows it safely, and why it failed."""
    # Checked first because apprise logs an unknown URL in full.
    problem = problem_with(url)
    if problem:
        return shown, problem
    import apprise

    _HIDDEN_IN_LIBRARY_LOGS.add(url)  # at DEBUG apprise logs where it posts, token and all
    plugin = apprise.Apprise.instantiate(url)
    if plugin is None:
        return shown, "apprise could not read this URL (its log says why)"
    # apprise masks each service's passwords, but keeps a json:// or form:// path
    shown = _redacted(plugin.url(privacy=True))
    # apprise's own defaults are 4 s; ours applies to every URL alike
    plugin.socket_connect_timeout = timeout_s
    plugin.socket_read_timeout = timeout_s
    if details:
        body = body + "\n\n" + "\n".join(f"{key}: {value}" for key, value in details.items())
    if not plugin.notify(body=body, title=title):
        return shown, "apprise could not deliver it (its log says why)"
    return shown, None


@cache
def _apprise_schemes() -> frozenset[str]:
    """Every scheme the installed apprise handles (about 0.5 s to load, hence the cache)."""
    import apprise

    schemes: set[str] = set()
    for service in apprise.Apprise().details()["schemas"]:
        schemes.update(service.get("protocols") or ())
        schemes.update(service.get("secure_protocols") or ())
    return frozenset(s.lower() for s in schemes)


def _scheme(url: str) -> str:
    """The URL's scheme in lower case; empty when there is none."""
    # urlsplit would also take "host:port" as a scheme; only "scheme://" counts here
    match = _SCHEME.match(url)
    return match.group(1).lower() if match else ""


def _redacted(url: str) -> str:
    """The URL with userinfo, path, query and fragment replaced by `***`."""
    try:
        parts = urlsplit(url)
        netloc = _host_port(parts)
    except ValueError:
        return "<unreadable URL>"
    if parts.username is not None or parts.password is not None:
        netloc = "***@" + netloc
    path = "/***" if parts.path.strip("/") else parts.path
    return urlunsplit((parts.scheme, netloc, path, "***" if parts.query else "",
                       "***" if parts.fragment else ""))


def _host_port(parts: SplitResult) -> str:
    """The netloc without its userinfo."""
    _ = parts.port  # raises ValueError for a port that is not a number
    return parts.netloc.rpartition("@")[2]


def _secret_parts(url: str) -> set[str]:
    """What of an apprise URL may be a secret: its userinfo, a host that is no DNS name or
    address (`tgram://BOTTOKEN/chat`), each step of its path, its query and fragment."""
    try:
        parts = urlsplit(url.strip())
    except ValueError:
        return {url}
    userinfo, _, host = parts.netloc.rpartition("@")
    found = {url.strip(), userinfo, *userinfo.split(":"), parts.path.strip("/"),
             *parts.path.split("/"), parts.query, parts.fragment,
             *(value for _, value in parse_qsl(parts.query))}
    if "." not in host:
        found.update({host, *host.split(":")})
    found = {part for part in found if len(part) >= _MIN_HIDDEN_CHARS}
    return found | {unquote(part) for part in found}


_MIN_HIDDEN_CHARS = 4  # shorter ones ("443", a chat's "42") would shred every line, hide little


class _HideAlertUrls(logging.Filter):
    """Masks the secret parts of the apprise URLs this process sent to in what apprise and
    urllib3 log: at DEBUG both give the full address they post to (Telegram's bot token is
    in its path)."""

    def __init__(self) -> None:
        super().__init__()
        self._secrets: list[str] = []

    def add(self, url: str) -> None:
        """Mask `url`'s secret parts from now on."""
        self._secrets = sorted(set(self._secrets) | _secret_parts(url), key=len, reverse=True)

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        masked = message
        for secret in self._secrets:
            masked = masked.replace(secret, "***")
        if masked != message:
            record.msg, record.args = masked, None
        return True


_HIDDEN_IN_LIBRARY_LOGS = _HideAlertUrls()
for _name in ("apprise", "urllib3.connectionpool", "urllib3.connection", "urllib3.util.retry"):
    logging.getLogger(_name).addFilter(_HIDDEN_IN_LIBRARY_LOGS)


def _scrubbed(text: str, url: str) -> str:
    """The text with every secret part of the URL (and the URL itself) replaced by `***`."""
    try:
        parts = urlsplit(url)
        secrets = [url, parts.netloc.rpartition("@")[0], parts.password, parts.query,
                   parts.fragment, parts.path.strip("/")]
    except ValueError:
        secrets = [url]
    for secret in sorted({s for s in secrets if s}, key=len, reverse=True):
        text = text.replace(secret, "***").replace(unquote(secret), "***")
    return text
