"""`dncq machines check`: which machines answer, how fast, and what they can do."""

from __future__ import annotations

from tests.jobs.cli.runner import dncq, table_rows
from tests.worker.simulator.sim_process import start_sim  # noqa: F401


def test_check_reports_reachable_and_offline_machines(elsewhere, add_machines):
    add_machines({"id": "ok1", "name": "Up", "model": "Fanuc 0i-F"},
                 {"id": "off1", "name": "Down", "model": "Mock", "options": {"offline": True}})
    result = dncq("machines", "check", "--all", width=200)
    assert result.exit_code == 1  # one machine did not answer
    reachable = {row["id"]: row["reachable"] for row in table_rows(result.output)}
    assert reachable["ok1"] == "yes" and reachable["off1"].startswith("no ")


def test_check_of_one_machine_that_answers_exits_0(elsewhere, add_machines):
    add_machines({"id": "ok1", "name": "Up", "model": "Mock"})
    result = dncq("machines", "check", "ok1")
    assert result.exit_code == 0 and "yes" in result.output


def test_check_names_the_model_as_registered_and_the_row_that_governs_it(settings, add_machines):
    from jobs import db
    from jobs.fleet import checks, registry

    add_machines({"id": "f18", "name": "Old", "model": "Fanuc 18i"},
                 {"id": "f0i", "name": "New", "model": "Fanuc 0i-F"})
    with db.session_scope(settings.resolved_database_url) as session:
        specs = [registry.get(session=session, machine_id=m) for m in ("f18", "f0i")]
    found = [checks.check(spec, data_dir=settings.data_dir)["model"] for spec in specs]
    assert found == ["Fanuc 18i (Fanuc (other models))", "Fanuc 0i-F"]


def test_check_all_goes_on_past_a_machine_that_answers_nonsense(elsewhere, add_machines):
    import threading
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    class Html(BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 (http.server's naming)
            body = b"<html>maintenance</html>"
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *_: object) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Html)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        add_machines({"id": "odd1", "name": "Odd", "model": "Gateway file server",
                      "transport": "gateway",
                      "options": {"url": f"http://127.0.0.1:{server.server_address[1]}",
                                  "machine_id": "x", "api_key": "k", "timeout_s": 5}},
                     {"id": "ok1", "name": "Up", "model": "Mock"})
        result = dncq("machines", "check", "--all", width=200)
    finally:
        server.shutdown()
    reachable = {row["id"]: row["reachable"] for row in table_rows(result.output)}
    assert result.exit_code == 1 and "Traceback" not in result.output
    assert reachable["odd1"].startswith("no ") and reachable["ok1"] == "yes"


def test_check_of_a_dnc_machine_shows_its_heartbeat_and_round_trip(
        settings, elsewhere, add_machines, start_sim) -> None:  # noqa: F811
    from jobs import db
    from jobs.fleet import checks, registry

    sim = start_sim()
    add_machines({"id": "dnc1", "name": "Lathe", "model": "Fanuc 0i-F", "transport": "dnc",
                  "options": {"host": "127.0.0.1", "port": sim.port}},
                 {"id": "ok1", "name": "Up", "model": "Mock"})
    with db.session_scope(settings.resolved_database_url) as session:
        specs = {m: registry.get(session=session, machine_id=m) for m in ("dnc1", "ok1")}
    link = checks.check(specs["dnc1"], data_dir=settings.data_dir)["link"]
    assert link["heartbeat"] is True and link["round_trip_ms"] > 0 and link["error"] is None
    assert checks.check(specs["ok1"], data_dir=settings.data_dir)["link"] is None  # no link

    result = dncq("machines", "check", "--all", width=200)  # every column shown whole
    heartbeat = {row["id"]: row["heartbeat"] for row in table_rows(result.output)}
    assert result.exit_code == 0 and heartbeat["dnc1"].startswith("ok ")
    assert heartbeat["ok1"] == ""


def test_check_says_the_free_space_where_the_transport_tells_it(settings, add_machines):
    import shutil

    from jobs import db
    from jobs.fleet import checks, registry

    add_machines({"id": "m1", "name": "Sim", "model": "Mock"},
                 {"id": "d1", "name": "Dnc", "model": "Fanuc 0i-F", "transport": "dnc",
                  "options": {"host": "127.0.0.1", "port": 1, "timeout_s": 1}})
    with db.session_scope(settings.resolved_database_url) as session:
        mock, dnc = (registry.get(session=session, machine_id=m) for m in ("m1", "d1"))

    told = checks.check(mock, data_dir=settings.data_dir)["free_bytes"]
    unreachable = checks.check(dnc, data_dir=settings.data_dir)

    assert abs(told - shutil.disk_usage(settings.data_dir).free) < 256 * 1024**2
    assert unreachable["reachable"] is False and unreachable["free_bytes"] is None


def test_check_fits_80_columns_with_what_each_machine_can_do_below(elsewhere, add_machines):
    add_machines({"id": "f18", "name": "Old lathe", "model": "Fanuc 18i"},
                 {"id": "off1", "name": "Down", "model": "Mock", "options": {"offline": True}})
    result = dncq("machines", "check", "--all", width=80)
    assert all(len(line) <= 80 for line in result.output.splitlines())
    measured = {row["id"]: row for row in table_rows(result.output)}
    abilities = {row["id"]: row for row in table_rows(result.output, which=1)}
    assert measured["f18"]["reachable"] == "yes" and measured["f18"]["name"] == "Old lathe"
    assert measured["off1"]["reachable"].startswith("no ")
    assert abilities["f18"]["model"] == "Fanuc 18i (Fanuc (other models))"
    assert abilities["f18"]["can"] == "lock, current program"
    assert abilities["off1"]["transport"] == "mock"
