"""The rules' own helpers: the request link they give."""

from __future__ import annotations

import pytest

from jobs.errors import ContractError, ErrorCode
from jobs.fleet import door
from jobs.fleet.registry import MachineSpec
from worker.transports.base import ConnectFailed
from worker.transports.optional import RequestLink
from worker.transports.serial_line import SerialTransport


def test_request_link_is_the_machines_link_when_its_transport_takes_requests(tmp_path):
    spec = MachineSpec(id="s1", name="Lathe", model="Fanuc 0i-F", transport="serial",
                       options={"url": "socket://127.0.0.1:9"})  # opened only when used

    with door.open_files(spec, data_dir=tmp_path) as files:
        link = files.request_link()

    assert isinstance(link, RequestLink)
    assert isinstance(files.transport.inner, SerialTransport)


def test_request_link_is_unsupported_on_a_transport_without_requests(tmp_path):
    spec = MachineSpec(id="m1", name="Sim", model="Mock", transport="mock")

    with door.open_files(spec, data_dir=tmp_path) as files, \
            pytest.raises(ContractError) as refused:
        files.request_link()

    assert refused.value.code == ErrorCode.UNSUPPORTED


def test_a_request_links_failures_come_as_the_transports_errors(tmp_path):
    spec = MachineSpec(id="s2", name="Lathe", model="Fanuc 0i-F", transport="serial",
                       options={"url": "socket://127.0.0.1:1"})  # nothing listens there

    with door.open_files(spec, data_dir=tmp_path) as files, \
            pytest.raises(ConnectFailed):
        files.request_link().receive_program(timeout_s=0.1)
