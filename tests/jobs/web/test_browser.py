"""The dashboard in a real headless browser against a real `dncq serve`, offline."""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from jobs import db
from jobs.inbox import service as inbox
from jobs.settings import Settings
from tests.jobs.helpers import wait_until
from tests.jobs.web import browser as b
from tests.jobs.web.conftest import signin_form

LIVE_TIMEOUT_MS = 90_000  # a followed job or run reaching its end


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[b.Served]:
    yield from b.serve(tmp_path_factory.mktemp("served"))


@pytest.fixture(scope="module")
def chromium() -> Iterator[Any]:
    yield from b.launch()


@pytest.fixture
def watched() -> Iterator[b.Watched]:
    """Fails the test when a page logged an error or asked for anything off the host."""
    found = b.Watched()
    yield found
    assert found.outside == [], "the dashboard asked for something off its host"
    assert found.errors == [], "a page logged console errors"


@pytest.fixture
def page(chromium: Any, served: b.Served, watched: b.Watched) -> Iterator[Any]:
    opened = b.offline_page(chromium, served.url, watched)
    yield opened
    opened.context.close()


def _expect() -> Any:
    from playwright.sync_api import expect

    return expect


def test_dncq_serve_prints_the_dashboards_address_beside_the_apis(served: b.Served) -> None:
    printed = served.log.read_text(errors="replace")

    assert f"dncq listening on {served.url}" in printed
    assert f"Dashboard: {served.url}/" in printed


def test_signing_in_and_out(page: Any, served: b.Served) -> None:
    expect = _expect()
    page.goto(served.url + "/jobs")
    expect(page).to_have_url(re.compile(r"/signin\?next=/jobs"))

    b.sign_in(page, served.url)
    expect(page.locator("h1")).to_contain_text("Fleet")
    page.click("text=Sign out")

    expect(page).to_have_url(served.url + "/signin")
    page.go_back()  # the fleet page, from the browser's memory: asked for again
    expect(page).to_have_url(re.compile(r"/signin"))
    expect(page.locator("text=Sign out")).to_have_count(0)
    page.goto(served.url + "/")
    expect(page).to_have_url(re.compile(r"/signin"))


def test_another_sites_page_cannot_sign_the_browser_in(chromium: Any, served: b.Served) -> None:
    forged = (f'<form method="post" action="{served.url}/signin">'
              f'<input name="name" value="admin"><input name="password" value="{b.API_KEY}">'
              '<input name="next" value="/"></form><script>document.forms[0].submit()</script>')
    context = chromium.new_context()
    context.route("http://elsewhere.test/**",
                  lambda r: r.fulfill(content_type="text/html", body=forged))
    try:
        page = context.new_page()
        page.goto("http://elsewhere.test/")
        page.wait_for_url(served.url + "/**")

        page.goto(served.url + "/")  # the victim comes to the dashboard later

        _expect()(page).to_have_url(re.compile(r"/signin"))
    finally:
        context.close()


def test_a_wrong_password_is_told_on_the_sign_in_page(page: Any, served: b.Served) -> None:
    page.goto(served.url + "/signin")
    page.fill("input[name=name]", "admin")
    page.fill("input[name=password]", "not-the-key")
    page.click("button[type=submit]")

    _expect()(page.locator("[role=alert]")).to_contain_text("wrong name or password")


def test_a_rollout_previewed_started_followed_live_and_its_failed_target_retried(
        page: Any, served: b.Served) -> None:
    expect = _expect()
    b.sign_in(page, served.url)
    page.goto(served.url + "/rollout")
    page.check("input[name=source][value=upload]")
    page.set_input_files("input[name=upload]", files=[{
        "name": "PART1.MPF", "mimeType": "text/plain", "buffer": b"G0 X0 Y0\nM30\n"}])
    page.check("input[name=ids][value='1011']")  # has a PART1.MPF already
    page.check("input[name=ids][value='1014']")
    page.click("button[value=preview]")

    preview = page.locator("#preview")
    expect(preview.locator("tr[data-machine='1011']")).to_contain_text("would fail")
    expect(preview.locator("tr[data-machine='1011']")).to_contain_text("142")
    expect(preview.locator("tr[data-machine='1014']")).to_contain_text("send as PART1.MPF")
    page.click("button[value=start]")

    expect(page).to_have_url(re.compile(r"/jobs/[0-9a-f]+$"))
    expect(page.locator("[data-live]")).to_have_text("finished", timeout=LIVE_TIMEOUT_MS)
    expect(page.locator("[data-retry]")).to_be_visible()
    expect(page.locator("[data-target='0'] [data-t-state]")).to_have_text("failed")
    expect(page.locator("[data-target='1'] [data-t-state]")).to_have_text("succeeded")
    job_url = page.url

    served.api.get("/api/cnc/deleteFile", params={"machineID": "1011", "fileName": "PART1.MPF"})
    page.goto(job_url)
    page.click("text=Retry failed targets")

    expect(page.locator(".notice")).to_contain_text("1 target(s) queued again")
    expect(page.locator("[data-target='0'] [data-t-state]")).to_have_text(
        "succeeded", timeout=LIVE_TIMEOUT_MS)
    expect(page.locator("[data-target='0'] [data-t-attempts]")).to_have_text("2")
    expect(page.locator("[data-retry]")).to_be_hidden()  # nothing failed is left


def test_a_double_click_on_start_starts_one_rollout(page: Any, served: b.Served) -> None:
    expect = _expect()
    b.sign_in(page, served.url)
    before = len(served.api.get("/api/jobs", params={"kind": "send"}).json())
    page.goto(served.url + "/rollout")
    page.check("input[name=source][value=upload]")
    page.set_input_files("input[name=upload]", files=[{
        "name": "TWICE.MPF", "mimeType": "text/plain", "buffer": b"G0 X0 Y0\nM30\n"}])
    page.check("input[name=ids][value='1014']")
    page.click("button[value=preview]")
    expect(page.locator("#preview tr[data-machine='1014']")).to_contain_text("send as TWICE.MPF")

    page.dblclick("button[value=start]")

    expect(page).to_have_url(re.compile(r"/jobs/[0-9a-f]+$"))
    page.wait_for_load_state("networkidle")
    jobs = served.api.get("/api/jobs", params={"kind": "send"}).json()
    assert len(jobs) == before + 1


def test_the_fleet_page_refreshes_itself_but_not_under_a_half_typed_search(
        page: Any, served: b.Served) -> None:
    b.sign_in(page, served.url)
    page.clock.install()
    page.goto(served.url + "/")
    page.evaluate("() => { window.loadedAt = 1; }")  # gone once the page reloads

    with page.expect_navigation():
        page.clock.run_for(31_000)  # idle: the page reloads itself
    assert page.evaluate("() => window.loadedAt === undefined")

    page.clock.install()
    page.goto(served.url + "/")
    page.fill("input[name=q]", "Lat")
    page.locator("h1").click()  # the search field loses focus, but is half done
    page.clock.run_for(95_000)

    assert page.input_value("input[name=q]") == "Lat"


def test_an_inbox_program_approved(page: Any, served: b.Served) -> None:
    expect = _expect()
    settings = Settings(data_dir=served.data_dir)
    with db.session_scope(settings.resolved_database_url) as session:
        item = inbox.receive(session=session, settings=settings, machine_id="1010",
                             data=b"%\nO0099 (NEW BRACKET)\nG21\nM30\n%\n", name="0099",
                             folder="VIPROS").id
    b.sign_in(page, served.url)
    page.goto(served.url + "/inbox")
    page.click(f"a[href='/inbox/{item}'] >> nth=0")

    expect(page.locator("pre.diff")).to_contain_text("no approved copy of VIPROS/0099")
    page.click("text=Approve into the library")

    expect(page.locator(".notice")).to_contain_text("Approved as VIPROS/0099 v1")
    page.goto(served.url + "/library?folder=VIPROS")
    expect(page.locator("a[href='/library/p/VIPROS/0099']")).to_be_visible()


def test_a_drip_feed_followed_live_and_stopped(page: Any, served: b.Served) -> None:
    expect = _expect()
    program = served.api.post(
        "/api/programs", content=(served.data_dir / "samples" / "BIGPART.NC").read_bytes(),
        headers={"content-type": "application/octet-stream"}).json()
    job = served.api.post("/api/jobs", json={
        "kind": "dnc_run", "machines": {"ids": ["2001"]}, "program": program["id"],
        "fileName": "BIGPART.NC"}).json()
    run_id = served.api.get(f"/api/jobs/{job['id']}").json()["runs"][0]["id"]
    b.sign_in(page, served.url)
    page.goto(f"{served.url}/runs/{run_id}")

    expect(page.locator("[data-run-state]")).to_have_text("running", timeout=LIVE_TIMEOUT_MS)
    expect(page.locator("[data-line]")).to_have_text(re.compile(r"^[1-9][0-9]*$"),
                                                     timeout=LIVE_TIMEOUT_MS)
    expect(page.locator("[data-rate]")).to_contain_text("blocks/s")
    page.click("text=Stop the run")

    expect(page.locator("[data-run-state]")).to_have_text("stopped", timeout=LIVE_TIMEOUT_MS)
    assert served.api.get(f"/api/runs/{run_id}").json()["state"] == "stopped"


def test_a_backup_found_by_day_opened_as_a_tree_compared_and_a_folder_restored(
        page: Any, served: b.Served) -> None:
    expect = _expect()
    jobs = [served.api.post("/api/jobs", json={"kind": "backup",
                                               "machines": {"ids": ["1016"]}}).json()["id"]
            for _ in range(2)]
    for job_id in jobs:  # its ZIP is assembled once every target is final
        wait_until(lambda j=job_id: served.api.get("/api/backups", params={"job": j}).json())
    [newest] = served.api.get("/api/backups", params={"job": jobs[1]}).json()
    day = newest["createdAt"][:10]
    b.sign_in(page, served.url)
    page.goto(f"{served.url}/backups")
    page.fill("input[name=day]", day)
    page.click("button:has-text('Show')")
    page.click(f"tr[data-backup='{newest['id']}'] a")

    tree = page.locator(".tree")
    expect(tree).to_contain_text("sample1.nc")
    page.select_option("select[name=second]", index=1)
    page.click("button:has-text('Compare')")
    expect(page.locator("h1")).to_contain_text("Compare")
    expect(page.locator("main")).to_contain_text("No difference")
    for folder, name in (("/1", "sample1.nc"), ("/1/1", "sample2.nc")):  # lost on the machine
        served.api.get("/api/cnc/deleteFile", params={"machineID": "1016", "fileName": name,
                                                      "dirAtCNC": folder})
    page.go_back()
    page.locator("form[data-folder='/1'] button").click()

    expect(page).to_have_url(re.compile(r"/jobs/[0-9a-f]+$"))
    expect(page.locator("h1")).to_contain_text("restore job")
    expect(page.locator("[data-job-state]")).to_have_text("succeeded", timeout=LIVE_TIMEOUT_MS)
    listing = served.api.get("/api/cnc/readAllPrograms", params={"machineID": "1016"}).json()
    assert {p["fileName"] for p in listing["programs"]} >= {"sample1.nc", "sample2.nc"}


def test_the_audit_trail_shows_a_named_users_dashboard_actions_under_its_name(
        page: Any, served: b.Served) -> None:
    expect = _expect()
    settings = Settings(data_dir=served.data_dir)
    with db.session_scope(settings.resolved_database_url) as session:
        item = inbox.receive(session=session, settings=settings, machine_id="1010",
                             data=b"%\nO0123 (AUDITED)\nG21\nM30\n%\n", name="0123",
                             folder="VIPROS").id
    b.sign_in(page, served.url)
    page.goto(served.url + "/admin/users")
    form = page.locator("#add-user")
    form.locator("input[name=name]").fill("petra")
    form.locator("select[name=role]").select_option("admin")
    form.locator("input[name=password]").fill("petra-password")
    form.locator("input[name=password_again]").fill("petra-password")
    form.locator("button[type=submit]").click()
    expect(page.locator(".notice")).to_contain_text("Added petra (admin)")
    page.click("text=Sign out")
    b.sign_in(page, served.url, "petra", "petra-password")

    page.goto(served.url + "/rollout")  # a rollout started from the page
    page.check("input[name=source][value=upload]")
    page.set_input_files("input[name=upload]", files=[{
        "name": "AUDIT1.MPF", "mimeType": "text/plain", "buffer": b"G0 X0\nM30\n"}])
    page.check("input[name=ids][value='1014']")
    page.click("button[value=preview]")
    page.click("button[value=start]")
    expect(page).to_have_url(re.compile(r"/jobs/[0-9a-f]+$"))
    job_id = page.url.rsplit("/", 1)[1]
    page.goto(f"{served.url}/inbox/{item}")  # an inbox program approved
    page.click("text=Approve into the library")
    expect(page.locator(".notice")).to_contain_text("Approved as VIPROS/0123")
    page.goto(served.url + "/admin/audit")
    page.select_option("select[name=who]", "petra")
    page.click("button:has-text('Show')")

    rows = page.locator("tr[data-event]")
    expect(rows.nth(0).locator("[data-action]")).to_have_text("approve inbox item")
    expect(rows.nth(0)).to_contain_text(str(item))
    expect(rows.nth(1).locator("[data-action]")).to_have_text("start rollout")
    expect(rows.nth(1)).to_contain_text(job_id)
    expect(rows.nth(2).locator("[data-action]")).to_have_text("sign in")
    for row in range(3):
        expect(rows.nth(row).locator("[data-who]")).to_contain_text("petra")
    page.goto(served.url + "/admin/audit?who=admin&action=add+user")
    expect(page.locator("tr[data-event]").first).to_contain_text("petra")


def test_an_admin_ends_the_lock_out_of_an_address_from_the_users_page(
        page: Any, served: b.Served) -> None:
    expect = _expect()
    b.sign_in(page, served.url)  # before the guesses: they lock this address's sign-in
    with httpx.Client(base_url=served.url, follow_redirects=False) as guesser:
        try:
            for _ in range(5):  # DNCQ_SIGNIN_MAX_FAILURES' default
                signin_form(guesser, name="admin", password="a stale copy of the key")
            assert signin_form(guesser, name="admin", password=b.API_KEY).status_code == 200
            page.goto(served.url + "/admin/users")
            row = page.locator("tr[data-lockout='127.0.0.1'][data-counted='admin sign-ins']")
            expect(row).to_contain_text("locked")
            expect(row.locator("td").nth(2)).to_have_text("5")  # the failures that locked it,
            expect(row.locator("time")).to_have_count(2)  # since when and until when

            row.locator("button:has-text('End lock-out')").click()  # confirmed (b.offline_page)

            expect(page.locator(".notice")).to_contain_text(
                "Ended the lock-out of 127.0.0.1 (admin sign-ins)")
            expect(page.locator("tr[data-lockout='127.0.0.1']")).to_have_count(0)
            assert signin_form(guesser, name="admin", password=b.API_KEY).status_code == 303
        finally:  # the module's other tests sign in from this address
            served.api.delete("/api/lockouts/127.0.0.1")


def _refusals_expected(watched: b.Watched) -> None:
    """The console's note of a 403 the test provoked is not a page's error."""
    watched.errors[:] = [e for e in watched.errors if "403 (Forbidden)" not in e]


def test_a_viewer_sees_no_destructive_control_and_is_refused_one_anyway(
        page: Any, served: b.Served, watched: b.Watched) -> None:
    expect = _expect()
    served.api.post("/api/users", json={"name": "vera", "password": "vera-password",
                                        "role": "viewer"}).raise_for_status()
    key = served.api.post("/api/keys", json={"name": "vera-key", "role": "viewer"}).json()
    program = _programs(served, "1010")[0]
    b.sign_in(page, served.url, "vera", "vera-password")
    page.goto(served.url + "/m/1010")
    expect(page.locator("h1")).to_contain_text("1010")
    listed = page.locator("table tr").count()

    assert listed > 1  # the machine's files are shown ...
    for control in ("button:has-text('Delete')", "button:has-text('Upload')",
                    "button:has-text('Make folder')", "form[action$='/delete']"):
        assert page.locator(control).count() == 0, control  # ... but nothing to change them
    page.goto(served.url + "/rollout")
    assert page.locator("button[value=start]").count() == 0
    # A delete forged from the viewer's own page, with its valid CSRF token: 403.
    status = page.evaluate("""async (name) => {
        const form = new FormData();
        form.append("csrf_token", document.querySelector("input[name=csrf_token]").value);
        form.append("dir", ""); form.append("name", name);
        return (await fetch("/m/1010/delete", {method: "POST", body: form})).status;
    }""", program)
    api = served.api.get("/api/cnc/deleteFile", params={"machineID": "1010", "fileName": program},
                         headers={"X-Api-Key": key["key"]})

    assert status == 403
    assert api.status_code == 403 and "viewer" in api.text
    assert program in _programs(served, "1010")  # nothing was deleted
    _refusals_expected(watched)


def _programs(served: b.Served, machine_id: str) -> list[str]:
    listing = served.api.get("/api/cnc/readProgramList", params={"machineID": machine_id})
    programs: list[str] = listing.json()["programs"]
    return programs


def test_a_form_sent_without_its_csrf_token_is_refused_and_changes_nothing(
        page: Any, served: b.Served, watched: b.Watched) -> None:
    expect = _expect()
    b.sign_in(page, served.url)
    page.goto(served.url + "/m/1010")
    delete = page.locator("form[action='/m/1010/delete']").first
    name = delete.locator("input[name=name]").get_attribute("value")
    delete.evaluate("form => form.querySelector('input[name=csrf_token]').remove()")
    delete.locator("button").click()  # the confirmation is accepted (b.offline_page)

    expect(page.locator("body")).to_contain_text("CSRF token is missing or wrong")
    page.goto(served.url + "/m/1010")
    expect(page.locator(f"form[action='/m/1010/delete'] input[value='{name}']")).to_have_count(1)
    _refusals_expected(watched)


PAGES = ["/", "/?view=table", "/m/1010", "/m/1016", "/jobs", "/rollout", "/backups",
         "/inbox", "/runs", "/library", "/library/p/VIPROS/0010", "/schedules", "/admin/users",
         "/admin/audit"]
SIZES = [(1280, 800), (800, 1280), (1920, 1080)]


def test_every_page_at_tablet_and_desktop_sizes_without_console_errors_or_outside_requests(
        chromium: Any, served: b.Served, watched: b.Watched,
        tmp_path: Path) -> None:
    shots = Path(os.environ.get("DNCQ_SCREENSHOTS") or tmp_path / "screenshots")
    shots.mkdir(parents=True, exist_ok=True)
    for width, height in SIZES:
        page = b.offline_page(chromium, served.url, watched, width=width, height=height)
        b.sign_in(page, served.url)
        for path in PAGES + _recent(served):
            answer = page.goto(served.url + path)
            assert answer is not None and answer.status == 200, path
            name = re.sub(r"[^A-Za-z0-9]+", "_", path).strip("_") or "fleet"
            page.screenshot(path=str(shots / f"{name}-{width}x{height}.png"), full_page=True)
        page.context.close()
    print(f"screenshots in {shots}")


# The words of a cell the browser laid out over more than one line: "TARGETS" shown as
# "TARGET" above "S", a job's id as "460b87ea" above "8f".
CUT_WORDS = """(selector) => {
  const cut = [];
  for (const cell of document.querySelectorAll(selector)) {
    const walker = document.createTreeWalker(cell, NodeFilter.SHOW_TEXT);
    for (let node = walker.nextNode(); node; node = walker.nextNode()) {
      for (const word of node.textContent.matchAll(/\\S+/g)) {
        const range = document.createRange();
        range.setStart(node, word.index);
        range.setEnd(node, word.index + word[0].length);
        const lines = new Set([...range.getClientRects()].map(r => Math.round(r.top)));
        if (lines.size > 1) cut.push(word[0]);
      }
    }
  }
  return cut;
}"""


def test_column_names_job_ids_and_kinds_are_never_cut_in_the_middle_of_a_word(
        chromium: Any, served: b.Served, watched: b.Watched) -> None:
    for kind, body in (("send", {"fileName": "WORDS.NC", "content": "%\nO0123\nM30\n%\n"}),
                       ("backup", {})):
        made = served.api.post("/api/jobs", json={"kind": kind, "machines": {"all": True},
                                                  **body})
        assert made.status_code == 202, made.text
    cut = []
    for width, height in SIZES[:2]:  # the tablet held either way
        page = b.offline_page(chromium, served.url, watched, width=width, height=height)
        b.sign_in(page, served.url)
        for path in PAGES:
            page.goto(served.url + path)
            cut += [f"{path} at {width}: {word}" for word in
                    page.evaluate(CUT_WORDS, "th, [data-job-id], [data-job-kind]")]
        page.context.close()

    assert cut == []


def _recent(served: b.Served) -> list[str]:
    """A job, a run, a backup (and two compared), an inbox item and a user, when the tests
    made them."""
    found = []
    for what, path in (("jobs", "/jobs/{id}"), ("runs", "/runs/{id}"),
                       ("backups", "/backups/{id}"), ("inbox", "/inbox/{id}")):
        listed = served.api.get(f"/api/{what}").json()
        if listed:
            found.append(path.format(id=listed[0]["id"]))
        if what == "runs" and listed:  # restarting a run from a block, its header previewed
            found.append(f"/runs/{listed[0]['id']}/restart")
        if what == "backups" and len(listed) > 1:
            found.append(f"/backups/diff?first={listed[1]['id']}&second={listed[0]['id']}")
    named = served.api.get("/api/users").json()
    if named:
        found.append(f"/admin/users/{named[0]['name']}")
    return found


def _finished(served: b.Served, made: Any) -> str:
    """The id of a job just made, once it has ended."""
    assert made.status_code in (200, 201, 202), made.text
    job_id = str(made.json()["id"])
    wait_until(lambda: served.api.get(f"/api/jobs/{job_id}", params={"limit": 0}).json()
               ["state"] not in ("queued", "running"))
    return job_id


def test_a_program_name_in_a_machines_jobs_is_never_cut_in_the_middle(
        chromium: Any, served: b.Served, watched: b.Watched) -> None:
    # A restore's "By" (restore of <job id>) took the room: BIGPART.NC read "BIGPART.N" above "C".
    send = {"kind": "send", "machines": {"ids": ["1016"]}, "fileName": "BIGPART.NC",
            "content": "%\nG0 X0\nM30\n%\n"}
    _finished(served, served.api.post("/api/jobs", json=send))
    replaced = _finished(served, served.api.post("/api/jobs", json={
        **send, "content": "%\nG0 X1\nM30\n%\n", "replace": True}))
    _finished(served, served.api.post(f"/api/jobs/{replaced}/restore-replaced"))
    page = b.offline_page(chromium, served.url, watched)  # the tablet held sideways
    b.sign_in(page, served.url)
    page.goto(served.url + "/m/1016")

    assert "BIGPART.NC" in page.inner_text("table")
    assert page.evaluate(CUT_WORDS, "[data-file-name]") == []
    page.context.close()


# How a cell holding `text` was laid out: the words of the text (its runs of letters and
# digits, between its separators) the browser cut over two lines, how many lines the text
# took, and whether the cell's table is wider than the window or scrolls sideways.
LAID_OUT = """(text) => {
  const cell = [...document.querySelectorAll("td")].find(td => td.textContent.includes(text));
  const node = document.createTreeWalker(cell, NodeFilter.SHOW_TEXT);
  const nodes = [];
  for (let n = node.nextNode(); n; n = node.nextNode()) nodes.push(n);
  const tops = rects => new Set([...rects].map(r => Math.round(r.top)));
  const cut = [];
  for (const n of nodes) {
    for (const word of n.textContent.matchAll(/[A-Za-z0-9]+/g)) {
      const range = document.createRange();
      range.setStart(n, word.index);
      range.setEnd(n, word.index + word[0].length);
      if (tops(range.getClientRects()).size > 1) cut.push(word[0]);
    }
  }
  const whole = document.createRange();
  whole.selectNodeContents(cell);
  const box = cell.closest(".scroll");
  return {cut, lines: tops(whole.getClientRects()).size,
          tableRight: cell.closest("table").getBoundingClientRect().right,
          window: document.documentElement.clientWidth,
          scrollsSideways: box.scrollWidth > box.clientWidth};
}"""


def _inbox_laid_out(chromium: Any, served: b.Served, watched: b.Watched, *, folder: str,
                    name: str) -> dict[str, Any]:
    """How the inbox table lays out a program received as `folder`/`name`, on a tablet
    held upright (800 × 1280)."""
    settings = Settings(data_dir=served.data_dir)
    with db.session_scope(settings.resolved_database_url) as session:
        inbox.receive(session=session, settings=settings, machine_id="1010",
                      data=b"%\nO1234\nM30\n%\n", name=name, folder=folder)
    page = b.offline_page(chromium, served.url, watched, width=800, height=1280)
    b.sign_in(page, served.url)
    page.goto(served.url + "/inbox")
    laid_out: dict[str, Any] = page.evaluate(LAID_OUT, f"{folder}/{name}")
    page.context.close()
    return laid_out


def test_a_long_path_in_a_table_wraps_at_its_separators_not_inside_a_word_on_an_upright_tablet(
        chromium: Any, served: b.Served, watched: b.Watched) -> None:
    shown = _inbox_laid_out(chromium, served, watched, folder="CAM/FIXTURE_PLATE_SECOND_OP",
                            name="O1234_ROUGHING.nc")

    assert shown["lines"] > 1  # the path is wider than its cell: it wraps
    assert shown["cut"] == []  # FIXTURE, SECOND, O1234, ROUGHING each whole on a line
    assert shown["tableRight"] <= shown["window"] and not shown["scrollsSideways"]


def test_a_word_too_long_for_its_cell_is_cut_and_its_table_still_fits_an_upright_tablet(
        chromium: Any, served: b.Served, watched: b.Watched) -> None:
    word = "FIXTUREPLATESECONDOPERATIONROUGHINGPASSWITHTHEBIGFACEMILL"
    shown = _inbox_laid_out(chromium, served, watched, folder="CAM", name=f"{word}.nc")

    assert shown["cut"] == [word]
    assert shown["tableRight"] <= shown["window"] and not shown["scrollsSideways"]


def test_every_table_fits_an_upright_tablet_without_scrolling_sideways(
        chromium: Any, served: b.Served, watched: b.Watched) -> None:
    page = b.offline_page(chromium, served.url, watched, width=800, height=1280)
    b.sign_in(page, served.url)
    wider = []
    for path in PAGES:
        page.goto(served.url + path)
        wider += [f"{path}: {width} px in {room} px" for width, room in page.evaluate(
            """() => [...document.querySelectorAll(".scroll")]
                 .map(box => [box.scrollWidth, box.clientWidth])
                 .filter(([width, room]) => width > room)""")]
    page.context.close()

    assert wider == []


# The dates and clocks a page shows that the browser laid out over more than one line:
# "2026-12-" above "06", "03:40:12" above "CET".
CUT_TIMES = """() => {
  const cut = [];
  const walker = document.createTreeWalker(document.body, NodeFilter.SHOW_TEXT);
  for (let node = walker.nextNode(); node; node = walker.nextNode()) {
    const said = /\\d{4}-\\d\\d-\\d\\d|\\d\\d:\\d\\d(:\\d\\d)?( [A-Z]{3,4}\\b| [+-]\\d{4})?/g;
    for (const value of node.textContent.matchAll(said)) {
      const range = document.createRange();
      range.setStart(node, value.index);
      range.setEnd(node, value.index + value[0].length);
      const lines = new Set([...range.getClientRects()].map(r => Math.round(r.top)));
      if (lines.size > 1) cut.push(value[0]);
    }
  }
  return cut;
}"""


def test_no_date_or_clock_is_cut_over_two_lines_and_no_table_scrolls_sideways(
        chromium: Any, served: b.Served, watched: b.Watched) -> None:
    made = served.api.post("/api/jobs", json={"kind": "backup", "machines": {"all": True}})
    _finished(served, made)
    cut, wider = [], []
    for width, height in SIZES[:2]:  # the tablet held either way
        page = b.offline_page(chromium, served.url, watched, width=width, height=height)
        b.sign_in(page, served.url)
        for path in PAGES + _recent(served):
            page.goto(served.url + path)
            cut += [f"{path} at {width}: {value}" for value in page.evaluate(CUT_TIMES)]
            wider += [f"{path} at {width}: {used} px in {room} px" for used, room in
                      page.evaluate("""() => [...document.querySelectorAll(".scroll")]
                          .map(box => [box.scrollWidth, box.clientWidth])
                          .filter(([used, room]) => used > room)""")]
        page.context.close()

    assert cut == []
    assert wider == []
