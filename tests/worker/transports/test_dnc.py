"""The `dnc` transport passes the conformance suite against the simulator (its own process)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.worker.simulator.sim_process import SimFactory, start_sim  # noqa: F401
from tests.worker.transports.contract import *  # noqa: F403
from tests.worker.transports.contract import put
from worker.transports import kind
from worker.transports.base import BadPath, Unsupported
from worker.transports.dnc import DncTransport
from worker.transports.drip import DripFeeder


@pytest.fixture
def transport(start_sim: SimFactory) -> Iterator[DncTransport]:  # noqa: F811
    dnc = start_sim().transport()
    yield dnc
    dnc.close()


def test_the_registry_opens_it_by_name() -> None:
    assert kind("dnc").cls is DncTransport


def test_it_is_a_drip_feeder_without_folders(transport: DncTransport) -> None:
    assert isinstance(transport, DripFeeder) and transport.capabilities.drip_feed
    with pytest.raises(Unsupported):
        transport.make_dir("SUB")


def test_one_connection_serves_many_calls(transport: DncTransport) -> None:
    for number in range(5):
        put(transport, f"P{number}.nc", b"G0\n")
        transport.list_dir("")
    assert len(transport.list_dir("")) == 5


def test_a_name_the_model_does_not_take_is_bad_path(start_sim: SimFactory) -> None:  # noqa: F811
    fanuc = start_sim("--model", "Fanuc 0i-F").transport()
    put(fanuc, "O1234", b"%\nO1234\nM30\n%\n")
    with pytest.raises(BadPath):
        put(fanuc, "PART.nc", b"G0\n")
    assert [e.name for e in fanuc.list_dir("")] == ["O1234"]
    fanuc.close()
