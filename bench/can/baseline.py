"""The baseline side: simulated nodes and a canopen network in this process, no card."""

from __future__ import annotations

import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager

import can
import canopen
from canopen.objectdictionary import ObjectDictionary
from canopen.sdo.client import SdoClient

from dbm_tools.network import Network
from dpm.cia301 import COB_ID_NMT, INITIALISING, OPERATIONAL, SDO_REQUEST_BASE, SDO_RESPONSE_BASE
from dpm.commands import NMT_START
from firmware.sim import SimulatedNetwork


@contextmanager
def in_process(network: Network) -> Iterator[tuple[SimulatedNetwork, canopen.Network]]:
    """``network``'s simulated nodes and a canopen network on a private virtual channel."""
    channel = f"cifemu-bench-baseline-{uuid.uuid4().hex}"
    sim_bus = can.Bus(interface="virtual", channel=channel)
    sim = SimulatedNetwork(network, sim_bus)
    sim.start()
    client = canopen.Network(can.Bus(interface="virtual", channel=channel))
    client.connect()
    try:
        yield sim, client
    finally:
        client.disconnect()
        sim.stop()
        sim_bus.shutdown()


def sdo_client(client: canopen.Network, node: int) -> SdoClient:
    sdo = SdoClient(SDO_REQUEST_BASE + node, SDO_RESPONSE_BASE + node,  # type: ignore[no-untyped-call]
                    ObjectDictionary())  # type: ignore[no-untyped-call]
    sdo.network = client
    client.subscribe(SDO_RESPONSE_BASE + node, sdo.on_response)
    return sdo


def start_all(sim: SimulatedNetwork, client: canopen.Network, timeout: float = 5.0) -> None:
    """Once every node has booted, NMT start to all; wait until all of them are OPERATIONAL."""
    deadline = time.monotonic() + timeout
    while any(node.nmt.code == INITIALISING for node in sim.nodes.values()):
        if time.monotonic() > deadline:
            raise RuntimeError("simulated nodes did not boot")
        time.sleep(0.001)
    client.send_message(COB_ID_NMT, bytes([NMT_START, 0]))
    while any(node.nmt.code != OPERATIONAL for node in sim.nodes.values()):
        if time.monotonic() > deadline:
            raise RuntimeError("simulated nodes did not reach OPERATIONAL")
        time.sleep(0.001)

