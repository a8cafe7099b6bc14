"""A real `dncq serve` in its own process and a real headless chromium driven by Playwright.

Playwright's own browser builds are downloaded by `playwright install`, which a shop
network (and CI) cannot do: the tests drive Debian's chromium package instead. Without it
or without Playwright they are skipped with the reason printed (failed under CI=true).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx

from tests.servers import free_port, stop_process, unavailable, wait_for_http

CHROMIUM = os.environ.get("DNCQ_CHROMIUM", "/usr/bin/chromium")
API_KEY = "browser-test-key-0123456789"
START_TIMEOUT_S = 60.0


@dataclass
class Served:
    """A running `dncq serve`: where, its data folder, and an API client with its key."""

    url: str
    data_dir: Path
    api: httpx.Client
    log: Path  # what it printed


def serve(tmp: Path) -> Iterator[Served]:
    """`dncq serve` with the demo fleet on a free port, its data under `tmp`."""
    port = free_port()
    env = {**os.environ, "DNCQ_DATA_DIR": str(tmp / "data"), "DNCQ_API_KEY": API_KEY,
           "DNCQ_PORT": str(port), "DNCQ_HOST": "127.0.0.1"}
    env.pop("DNCQ_DATABASE_URL", None)
    env.pop("DNCQ_BROKER_URL", None)
    log_path = tmp / "serve.log"
    log = log_path.open("wb")
    proc = subprocess.Popen([sys.executable, "-m", "jobs.cli", "serve"], cwd=tmp, env=env,
                            stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    # Connections idle for 2 s are not reused: uvicorn closes them after 5 s, and a POST
    # sent as it does so met "Server disconnected without sending a response".
    api = httpx.Client(base_url=url, headers={"X-Api-Key": API_KEY}, timeout=60,
                       limits=httpx.Limits(keepalive_expiry=2.0))
    try:
        wait_for_http(lambda: api.get("/api/health"), START_TIMEOUT_S)
        yield Served(url, tmp / "data", api, log_path)
    finally:
        api.close()
        stop_process(proc)
        log.close()


def launch() -> Iterator[Any]:
    """A headless chromium, or a skip saying what is missing."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        unavailable("playwright is not installed (pip install playwright)")
    if not (Path(CHROMIUM).is_file() or shutil.which(CHROMIUM)):
        unavailable(f"no chromium at {CHROMIUM} (apt-get install chromium)")
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        try:
            yield browser
        finally:
            browser.close()


@dataclass
class Watched:
    """What a page did that it should not: console errors, requests off the host."""

    errors: list[str] = field(default_factory=list)
    outside: list[str] = field(default_factory=list)


def offline_page(browser: Any, url: str, watched: Watched, *, width: int = 1280,
                 height: int = 800) -> Any:
    """A page that can reach only the server at `url`: every other request is aborted
    and noted, as a shop network without internet would."""
    host = urlsplit(url).netloc
    context = browser.new_context(viewport={"width": width, "height": height})

    def route(r: Any) -> None:
        if urlsplit(r.request.url).netloc == host:
            r.continue_()
        else:
            watched.outside.append(r.request.url)
            r.abort()

    context.route("**/*", route)
    page = context.new_page()
    page.on("console", lambda m: watched.errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda exc: watched.errors.append(str(exc)))
    page.on("dialog", lambda dialog: dialog.accept())  # the confirmations say yes
    return page


def sign_in(page: Any, url: str, name: str = "admin", password: str = API_KEY) -> None:
    """Sign in through the sign-in page."""
    page.goto(url + "/signin")
    page.fill("input[name=name]", name)
    page.fill("input[name=password]", password)
    page.click("button[type=submit]")
    page.wait_for_url(url + "/")
