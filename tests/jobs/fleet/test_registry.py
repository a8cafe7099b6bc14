"""The machine registry: fleet-file import and the admin API `/api/machines`."""

from __future__ import annotations

import sys
import textwrap

import pytest

from jobs import db
from jobs.errors import ContractError
from jobs.fleet import door, fleet_file, registry
from jobs.settings import Settings

FLEET = """
machines:
  - id: 1010
    name: Lathe-A
    model: Fanuc 0i-F
    tags: [lathes]
  - id: mill-b
    name: Mill-B
    model: Siemens 840D
    max_concurrent: 2
"""
MOCK = {"id": "m1", "name": "Sim", "model": "Mock"}


def import_text(settings: Settings, text: str) -> tuple[int, int]:
    """Parse and import a fleet file as `dncq machines import` does."""
    parsed = fleet_file.parse_fleet(textwrap.dedent(text))
    with db.session_scope(settings.resolved_database_url) as session:
        return fleet_file.import_fleet(session=session, machines=parsed,
                                       data_dir=settings.data_dir)


def registered(settings: Settings) -> list[registry.MachineSpec]:
    with db.session_scope(settings.resolved_database_url) as session:
        return registry.list_all(session=session)


# -- fleet files -------------------------------------------------------------------------


def test_importing_a_fleet_file_twice_keeps_one_row_per_machine(settings):
    first = import_text(settings, FLEET)
    second = import_text(settings, FLEET)

    assert (first, second) == ((2, 0), (0, 2))
    assert [m.id for m in registered(settings)] == ["1010", "mill-b"]


def test_importing_a_changed_fleet_file_updates_the_machines(settings):
    import_text(settings, FLEET)

    import_text(settings, FLEET.replace("Lathe-A", "Lathe-A2").replace("[lathes]", "[hall-2]"))

    lathe = registered(settings)[0]
    assert (lathe.name, lathe.tags) == ("Lathe-A2", ["hall-2"])


def test_numeric_id_in_a_fleet_file_is_read_as_text():
    parsed = fleet_file.parse_fleet(FLEET)

    assert parsed[0].id == "1010"


@pytest.mark.parametrize("written", ["0010", "010", "10.10", "0x1F"])
def test_id_that_yaml_would_turn_into_another_number_keeps_its_digits(written):
    text = f"machines:\n  - {{id: {written}, name: A, model: Mock}}\n"

    assert fleet_file.parse_fleet(text)[0].id == written


BAD_ENTRIES = {
    "unknown model": "{id: bad, name: B, model: Zeiss}",
    "unknown transport": "{id: bad, name: B, model: Mock, transport: telnet}",
    "bad option": "{id: bad, name: B, model: Mock, options: {latency_ms: -5}}",
    "unknown option": "{id: bad, name: B, model: Mock, options: {colour: red}}",
    "root outside the model's roots": "{id: bad, name: B, model: Siemens 840D, root: /etc}",
}


@pytest.mark.parametrize("entry", BAD_ENTRIES.values(), ids=BAD_ENTRIES.keys())
def test_a_bad_entry_rejects_the_whole_fleet_file_naming_the_entry(settings, entry):
    text = f"machines:\n  - {{id: good, name: G, model: Mock}}\n  - {entry}\n"

    with pytest.raises(fleet_file.FleetFileError, match=r"entry 2 \(id bad\)"):
        import_text(settings, text)

    assert registered(settings) == []


@pytest.mark.parametrize("entry", [
    "{model: FTP server, transport: ftp, options: {host: 'ftp://cnc:Hall2-pw@10.0.0.5'}}",
    "{model: FTP server, transport: ftp, options: {host: 'cnc:Hall2-pw@10.0.0.5'}}",
    "{model: Shared folder, transport: share, options: {server: '//cnc:Hall2-pw@nas', "
    "share: nc}}",
])
def test_a_host_given_as_a_url_with_its_password_is_refused_without_repeating_it(entry):
    text = f"machines:\n  - {{id: bad, name: B, {entry[1:]}\n"

    with pytest.raises(fleet_file.FleetFileError, match="not a URL") as refused:
        fleet_file.parse_fleet(text)

    assert "Hall2-pw" not in str(refused.value)


def test_a_machine_stored_with_a_url_host_keeps_its_password_out_of_errors_and_log(
        settings, caplog):
    # registered before hosts were checked: its options no longer load when it is opened
    spec = registry.MachineSpec(id="old", name="Old", model="FTP server", transport="ftp",
                                options={"host": "ftp://cnc:Hall2-pw@10.0.0.5"})

    with pytest.raises(ContractError) as refused:
        door.open_files(spec, data_dir=settings.data_dir)

    assert "Hall2-pw" not in str(refused.value)
    assert "Hall2-pw" not in caplog.text


@pytest.mark.parametrize(("line", "problem"), [
    ("options: {host: h, user: cnc, password: Hall2-pw: x}", "line 2, column 106: expected "
     "',' or '}', but got ':' (while parsing a flow mapping)"),
    ('options: {host: h, user: cnc, password: "Hall2-pw', "line 3, column 1: found "
     "unexpected end of stream (while scanning a quoted scalar)"),
])
def test_a_fleet_file_that_is_not_yaml_is_refused_naming_where_without_quoting_its_lines(
        client, line, problem):
    fleet = f"machines:\n  - {{id: f1, name: F, model: FTP server, transport: ftp, {line}\n"

    answer = client.post("/api/machines/import", json={"fleet": fleet})

    assert answer.status_code == 422
    assert answer.json()["statusMsg"] == f"a fleet file is YAML, and this is not: {problem}"
    assert "Hall2-pw" not in answer.text
    assert client.get("/api/machines").json() == []


def test_a_key_given_twice_in_one_machine_is_refused_naming_where(settings):
    # YAML keeps the last: the second options would drop the first's tls and password
    text = ("machines:\n  - id: f1\n    name: F\n    model: FTP server\n    transport: ftp\n"
            "    options: {host: 10.0.0.5, user: cnc, password: Hall2-pw, tls: true}\n"
            "    options: {host: 10.0.0.6}\n")

    with pytest.raises(fleet_file.FleetFileError) as refused:
        import_text(settings, text)

    assert str(refused.value) == ("a fleet file is YAML, and this is not: line 7, column 5: "
                                  "found 'options' twice in one mapping")
    assert "Hall2-pw" not in str(refused.value)


def test_the_same_id_twice_in_a_fleet_file_is_refused(settings):
    text = "machines:\n  - {id: a, name: A, model: Mock}\n  - {id: a, name: B, model: Mock}\n"

    with pytest.raises(fleet_file.FleetFileError, match="appears twice"):
        import_text(settings, text)


def test_a_root_on_one_of_the_model_roots_is_accepted(settings):
    import_text(settings, "machines:\n  - {id: f, name: F, model: Fanuc 0i-F, "
                          "root: //MEMCARD/}\n")

    assert registered(settings)[0].root == "//MEMCARD/"


# -- the admin API ---------------------------------------------------------------------------


def test_post_machine_adds_it_and_answers_201(client):
    response = client.post("/api/machines", json=MOCK)

    assert response.status_code == 201
    assert client.get("/api/machines").json()[0]["id"] == "m1"


def test_post_of_an_existing_machine_answers_409(client):
    client.post("/api/machines", json=MOCK)

    response = client.post("/api/machines", json={**MOCK, "name": "Other"})

    assert response.status_code == 409
    assert client.get("/api/machines/m1").json()["name"] == "Sim"


def test_a_root_nested_past_500_characters_is_registered_whole(database_url, settings):
    root = "/" + "/".join("R" * 99 for _ in range(7))  # 700 characters, a path dncq takes
    with db.session_scope(database_url) as session:
        registry.upsert(session=session, machine_in=registry.MachineIn.model_validate(
            {"id": "deep", "name": "Deep", "model": "Mock", "root": root}),
            data_dir=settings.data_dir)
    with db.session_scope(database_url) as session:
        assert registry.get(session=session, machine_id="deep").root == root


def test_get_machine_shows_it_with_its_default_root(client):
    client.post("/api/machines", json={**MOCK, "model": "Siemens 840D"})

    body = client.get("/api/machines/m1").json()

    assert (body["id"], body["root"], body["governing_model"]) == ("m1", "mpf.dir",
                                                                   "Siemens 840D")


def test_get_of_an_unknown_machine_answers_404(client):
    response = client.get("/api/machines/nope")

    assert response.status_code == 404


def test_get_of_an_unknown_machine_says_10003(client):
    body = client.get("/api/machines/nope").json()

    assert body["errorCode"] == 10003


@pytest.mark.parametrize(("largest_hinted", "said"), [
    (3, "Invalid MachineID (1O01) (did you mean 1001?)"),
    (2, "Invalid MachineID (1O01)")])  # a fleet too large to compare every id on each miss
def test_get_of_a_mistyped_machine_names_the_one_meant_in_a_fleet_small_enough(
        client, add_machines, monkeypatch, largest_hinted: int, said: str):
    add_machines(*({"id": m, "name": m, "model": "Mock"} for m in ("1001", "1016", "2001")))
    monkeypatch.setattr(registry, "HINTED_FLEET", largest_hinted)

    body = client.get("/api/machines/1O01").json()

    assert (body["errorCode"], body["statusMsg"]) == (10003, said)


def test_put_machine_replaces_its_values(client):
    client.post("/api/machines", json=MOCK)

    response = client.put("/api/machines/m1", json={**MOCK, "name": "Renamed", "tags": ["x"]})

    assert response.status_code == 200
    assert client.get("/api/machines/m1").json()["name"] == "Renamed"
    assert len(client.get("/api/machines").json()) == 1


def test_a_machine_read_edited_and_put_back_keeps_its_secret(client, tmp_path):
    from tests.worker.transports.ftp_server import PASSWORD, ftp_server_of

    with ftp_server_of("plain", tmp_path) as server:
        (server.home / "O1000.nc").write_text("%\nM30\n%\n")
        client.post("/api/machines", json={"id": "f1", "name": "Lathe", "model": "Fanuc 0i-F",
                                           "transport": "ftp", "options": server.options})
        shown = client.get("/api/machines/f1").json()
        assert shown["options"]["password"] == registry.SECRET_MASK != PASSWORD

        response = client.put("/api/machines/f1", json={**shown, "name": "Lathe 2"})

        assert response.status_code == 200, response.json()
        listing = client.get("/api/cnc/readProgramList", params={"machineID": "f1"}).json()
        assert listing["programs"] == ["O1000.nc"], listing  # it logged in


def test_a_masked_secret_is_not_kept_for_another_host(client):
    ftp = {"id": "f1", "name": "Lathe", "model": "Fanuc 0i-F", "transport": "ftp",
           "options": {"host": "10.0.0.5", "user": "cnc", "password": "s3cret"}}
    client.post("/api/machines", json=ftp)
    shown = client.get("/api/machines/f1").json()

    response = client.put("/api/machines/f1", json={
        **shown, "options": {**shown["options"], "host": "attacker.example"}})

    assert response.status_code == 422
    assert "give the secret itself" in response.json()["statusMsg"]
    assert client.get("/api/machines/f1").json()["options"]["host"] == "10.0.0.5"


def test_a_masked_secret_for_a_new_machine_is_refused(client):
    response = client.put("/api/machines/f2", json={
        "id": "f2", "name": "Lathe", "model": "Fanuc 0i-F", "transport": "ftp",
        "options": {"host": "127.0.0.1", "password": registry.SECRET_MASK}})

    assert response.status_code == 422
    assert "give the secret itself" in response.json()["statusMsg"]
    assert client.get("/api/machines/f2").status_code == 404


def test_a_default_root_put_back_follows_a_change_of_model(client):
    client.post("/api/machines", json={**MOCK, "model": "Siemens 840D"})
    shown = client.get("/api/machines/m1").json()
    assert shown["root"] == "mpf.dir"

    client.put("/api/machines/m1", json={**shown, "model": "Fanuc 0i-F"})

    assert client.get("/api/machines/m1").json()["root"] == "//CNC_MEM/"


def test_put_with_another_id_in_the_body_is_refused(client):
    client.post("/api/machines", json=MOCK)

    response = client.put("/api/machines/m1", json={**MOCK, "id": "m2"})

    assert response.status_code == 422
    assert [m["id"] for m in client.get("/api/machines").json()] == ["m1"]


def test_delete_machine_removes_it(client):
    client.post("/api/machines", json=MOCK)

    response = client.delete("/api/machines/m1")

    assert response.status_code == 204
    assert client.get("/api/machines/m1").status_code == 404


def test_delete_of_an_unknown_machine_answers_404(client):
    assert client.delete("/api/machines/nope").status_code == 404


def test_post_machine_with_a_root_outside_the_model_roots_is_refused(client):
    response = client.post("/api/machines", json={**MOCK, "model": "Siemens 840D", "root": "/etc"})

    assert response.status_code == 422
    assert "/etc" in response.json()["statusMsg"]
    assert client.get("/api/machines").json() == []


def test_post_machine_with_an_unknown_encoding_is_refused(client):
    response = client.post("/api/machines", json={**MOCK, "encoding": "bogus"})

    assert response.status_code == 400
    assert "unknown encoding 'bogus'" in response.json()["statusMsg"]
    assert client.get("/api/machines").json() == []


def test_post_machine_with_bad_options_names_the_option_in_one_line(client):
    response = client.post("/api/machines", json={**MOCK, "options": {"latency_ms": -1}})

    assert response.status_code == 422
    assert response.json()["statusMsg"] == \
        "options.latency_ms: Input should be greater than or equal to 0"
    assert client.get("/api/machines").json() == []


@pytest.mark.parametrize(("transport", "options"), [
    ("octoprint", {"api_key": "abcd1234"}), ("moonraker", {}),
    ("gateway", {"api_key": "k", "machine_id": "7"})])
def test_a_file_servers_url_with_credentials_is_refused_before_anyone_sees_them(
        client, transport, options):
    response = client.post("/api/machines", json={
        "id": "3001", "name": "Behind a proxy", "model": "Mock", "transport": transport,
        "options": {"url": "http://u:UrlPassw0rd@127.0.0.1:18305/", **options}})

    assert response.status_code == 422
    assert response.json()["statusMsg"] == \
        "options.url: url must not carry credentials; give the key as api_key"
    assert "UrlPassw0rd" not in response.text
    assert client.get("/api/machines").json() == []


@pytest.mark.parametrize(("transport", "options"), [
    ("octoprint", {"api_key": "abcd1234"}), ("moonraker", {}),
    ("gateway", {"api_key": "k", "machine_id": "7"})])
@pytest.mark.parametrize("url", ["http://127.0.0.1:18305/?apikey=UrlPassw0rd",
                                 "http://127.0.0.1:18305/#UrlPassw0rd"])
def test_a_file_servers_url_with_a_query_or_fragment_is_refused_before_anyone_sees_it(
        client, transport, options, url):
    response = client.post("/api/machines", json={
        "id": "3001", "name": "Behind a proxy", "model": "Mock", "transport": transport,
        "options": {"url": url, **options}})

    assert response.status_code == 422
    assert response.json()["statusMsg"] == \
        "options.url: url must not carry a query or fragment; give the key as api_key"
    assert "UrlPassw0rd" not in response.text
    assert client.get("/api/machines").json() == []


@pytest.mark.parametrize("folder", ["/etc", "../../etc", "a/../../b", "C:\\x"])
def test_a_mock_machine_cannot_keep_its_storage_outside_the_data_folder(client, folder):
    response = client.post("/api/machines", json={**MOCK, "options": {"folder": folder}})

    assert response.status_code == 422
    assert response.json()["statusMsg"].startswith("options.folder: ")
    assert client.get("/api/machines").json() == []


def test_post_machine_with_an_unknown_model_answers_400(client):
    response = client.post("/api/machines", json={**MOCK, "model": "Zeiss"})

    assert response.status_code == 400
    assert "unknown controller model" in response.json()["statusMsg"]


@pytest.mark.parametrize("folder", ["m2/files", "m2\\files", "m2/files/sub", ".hidden"])
def test_a_mock_machine_cannot_keep_its_state_in_another_machines_storage(client, folder):
    response = client.post("/api/machines", json={**MOCK, "options": {"folder": folder}})

    assert response.status_code == 422
    assert response.json()["statusMsg"].startswith("options.folder: ")
    assert client.get("/api/machines").json() == []


def test_two_mock_machines_may_share_one_folder(client, settings):
    for machine_id in ("m1", "m2"):
        client.post("/api/machines", json={**MOCK, "id": machine_id,
                                           "options": {"folder": "shared"}})
    sent = client.post("/api/cnc/sendFile", params={"machineID": "m1", "fileName": "P1.nc"},
                       json={"content": "G0\n"}).json()

    assert sent["errorCode"] == 0
    listing = client.get("/api/cnc/readProgramList", params={"machineID": "m2"}).json()
    assert listing["programs"] == ["P1.nc"]


def test_a_mock_machine_whose_folder_links_into_another_machines_storage_is_refused(
        client, settings):
    client.post("/api/machines", json={**MOCK, "id": "m2"})
    client.get("/api/cnc/readProgramList", params={"machineID": "m2"})  # its storage exists
    (settings.data_dir / "mock" / "m1").symlink_to(settings.data_dir / "mock" / "m2" / "files")
    client.post("/api/machines", json=MOCK)

    body = client.get("/api/cnc/readProgramList", params={"machineID": "m1"}).json()

    assert body["errorCode"] == 20010
    assert "link out of data/mock/ or into another machine's storage" in body["statusMsg"]
    assert sorted(p.name for p in (settings.data_dir / "mock" / "m2" / "files").iterdir()) == []


def test_a_bad_options_json_answers_a_clear_error_and_the_other_machines_carry_on(
        client, settings):
    for machine_id in ("m1", "m2"):
        client.post("/api/machines", json={**MOCK, "id": machine_id})
    folder = settings.data_dir / "mock" / "m1"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "options.json").write_text('{"latency_ms": "slow"}')

    bad = client.get("/api/cnc/readProgramList", params={"machineID": "m1"}).json()
    good = client.get("/api/cnc/readProgramList", params={"machineID": "m2"}).json()

    assert bad["errorCode"] == 20006
    assert bad["statusMsg"].startswith("options.json of this mock machine is not valid: "
                                       "latency_ms: ")
    assert good == {"dirAtCNC": "/", "programs": [], "subDirs": []}


# -- a share over SMB on a host without the smb extra -------------------------------------
# smbprotocol is installed here, so its absence is simulated: `import smbclient` fails as it
# does where the package is missing.

SMB_SHARE = {"id": "nas1", "name": "NAS", "model": "Mock", "transport": "share",
             "options": {"server": "127.0.0.1", "share": "cnc", "user": "u", "password": "p"}}
SMB_FLEET = """
machines:
  - id: nas1
    name: NAS
    model: Mock
    transport: share
    options: {server: 127.0.0.1, share: cnc}
"""


@pytest.fixture
def no_smb_package(monkeypatch):
    """`import smbclient` raises ImportError, as on a host without `dncq[smb]`."""
    monkeypatch.setitem(sys.modules, "smbclient", None)


def test_api_refuses_an_smb_share_without_the_smb_extra_naming_it(client, settings,
                                                                   no_smb_package):
    response = client.post("/api/machines", json=SMB_SHARE)

    assert response.status_code == 422, response.text
    assert 'pip install "dncq[smb]"' in response.json()["statusMsg"]
    assert registered(settings) == []


def test_fleet_import_refuses_an_smb_share_without_the_smb_extra_naming_it(settings,
                                                                           no_smb_package):
    with pytest.raises(fleet_file.FleetFileError, match=r'pip install "dncq\[smb\]"'):
        import_text(settings, SMB_FLEET)

    assert registered(settings) == []


def test_mounted_share_needs_no_smb_extra(client, tmp_path, no_smb_package):
    machine = {"id": "mnt1", "name": "Mounted", "model": "Mock", "transport": "share",
               "options": {"path": str(tmp_path)}}

    assert client.post("/api/machines", json=machine).status_code == 201


def test_smb_share_is_accepted_where_the_smb_extra_is_installed(client):
    assert client.post("/api/machines", json=SMB_SHARE).status_code == 201


# -- machines that take requests ------------------------------------------------------------


@pytest.mark.parametrize("database", ["sqlite", "postgresql"])
def test_only_enabled_machines_with_request_settings_are_looked_at_for_requests(
        request, settings, database):
    # Workers ask this every few seconds: the database must pick the machines, on both.
    url = (settings.resolved_database_url if database == "sqlite"
           else request.getfixturevalue("postgres_url"))
    serial = {"model": "Fanuc 0i-F", "transport": "serial",
              "options": {"url": "socket://127.0.0.1:4001"}}
    entries = [
        {"id": "drop", "name": "D", "model": "Mock", "requests": {"enabled": True,
                                                                 "drop_folder": "REQ"}},
        {"id": "plain", "name": "P", "model": "Mock"},
        {"id": "off", "name": "O", "model": "Mock", "enabled": False,
         "requests": {"enabled": True, "drop_folder": "REQ"}},
        {"id": "line", "name": "L", **serial, "requests": {"enabled": True}},
        {"id": "quiet-line", "name": "Q", **serial},
    ]
    with db.session_scope(url) as session:
        for entry in entries:
            registry.upsert(session=session, machine_in=registry.MachineIn.model_validate(entry),
                            data_dir=settings.data_dir)
    with db.session_scope(url) as session:
        every = [m.id for m in registry.taking_requests(session=session)]
        on_lines = [m.id for m in registry.taking_requests(session=session, kinds=["serial"])]

    assert every == ["drop", "line"]
    assert on_lines == ["line"]
