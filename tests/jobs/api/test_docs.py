"""The API docs pages work on a network without internet: every file they load comes from dncq."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient

from jobs.api.app import create_app

# What a browser fetches for the page: scripts, styles, icons, and the spec the page reads.
REFERENCE = re.compile(r"""(?:src|href|spec-url)="([^"]+)"|url: '([^']+)'""")


@pytest.fixture
def browser(settings) -> TestClient:
    """A browser: it sends no API key."""
    return TestClient(create_app(settings))


def references(html: str) -> list[str]:
    return [a or b for a, b in REFERENCE.findall(html)]


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_page_names_no_other_host(browser, page):
    html = browser.get(page).text

    assert len(references(html)) >= 3  # script, icon, spec: the pattern still finds them
    assert re.findall(r"https?:|//[a-z]", html) == []


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_every_file_a_docs_page_loads_is_served_without_a_key(browser, page):
    found = {ref: browser.get(ref).status_code for ref in references(browser.get(page).text)}

    assert set(found.values()) == {200}, found


def test_the_swagger_ui_script_served_is_the_script_itself(browser):
    response = browser.get("/docs-assets/swagger-ui-bundle.js")

    assert response.headers["content-type"].startswith(("text/javascript",
                                                        "application/javascript"))
    assert "SwaggerUIBundle" in response.text
