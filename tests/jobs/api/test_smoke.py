"""The API answers the seed's first example on the demo fleet."""


def test_read_program_list_of_demo_fanuc_returns_its_root_and_programs(client, demo_fleet):
    body = client.get("/api/cnc/readProgramList", params={"machineID": "1010"}).json()
    assert body["dirAtCNC"] == "//CNC_MEM/"
    assert "1234" in body["programs"]
    assert body["subDirs"] == ["USER"]
