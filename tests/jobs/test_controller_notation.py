"""Results say what the machine has, in the controller's notation: the name a Fanuc stored a
program under, and paths as the control writes them (`TNC:\\nc_prog\\...`), not dncq's
storage paths."""

from __future__ import annotations

from tests.jobs.helpers import wait_done

FANUC_PROGRAM = "%\nO0077\nG0 X0\nM30\n%\n"


def test_a_send_to_a_fanuc_says_the_name_the_program_was_stored_under(queue_client,
                                                                      add_machines):
    add_machines({"id": "lathe", "name": "Lathe", "model": "Fanuc 0i-F"})
    job_id = queue_client.post("/api/jobs", json={
        "kind": "send", "content": FANUC_PROGRAM,
        "targets": [{"machineID": "lathe", "fileName": "part.nc"}]}).json()["id"]

    [target] = wait_done(queue_client, job_id)["targets"]

    assert target["errorCode"] == 0
    assert target["statusMsg"] == "stored as //CNC_MEM/O0077"


def test_a_send_stored_under_the_name_given_says_nothing_more(queue_client, add_machines):
    add_machines({"id": "sim", "name": "Sim", "model": "Mock"})
    job_id = queue_client.post("/api/jobs", json={
        "kind": "send", "content": "G0 X0\n",
        "targets": [{"machineID": "sim", "fileName": "P.nc"}]}).json()["id"]

    [target] = wait_done(queue_client, job_id)["targets"]

    assert target["errorCode"] == 0 and target["statusMsg"] is None


def test_an_error_names_the_path_as_the_control_writes_it(client, add_machines):
    add_machines({"id": "tnc", "name": "Mill", "model": "Heidenhain TNC640"})

    missing = client.get("/api/cnc/deleteFile",
                         params={"machineID": "tnc", "fileName": "part.h"}).json()
    no_folder = client.get("/api/cnc/readProgramList",
                           params={"machineID": "tnc", "dirAtCNC": "TNC:\\nc_prog\\gone"}).json()

    assert missing["errorCode"] == 158
    assert "TNC:\\nc_prog\\part.h" in missing["statusMsg"]
    assert no_folder["errorCode"] == 158
    assert "TNC:\\nc_prog\\gone" in no_folder["statusMsg"]
    assert "TNC/" not in missing["statusMsg"] + no_folder["statusMsg"]
