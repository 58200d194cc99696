"""The work a cold start from flash costs the card, counted, not timed (issue 22).

A card with a stored database of many nodes boots them at every cold start: its CPU per
boot competes with the nodes' on a small machine, so the work per start and per node is
bounded here by counting calls, which a loaded machine does not change. The card and its
simulated nodes run in this process on a fresh ``virtual`` channel, as ``cifemu firmware
--simulate`` runs them; a counting wrapper around a real function is the only stand-in,
and it calls through.
"""

from __future__ import annotations

import sys
import threading
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import can
import pytest

import firmware.flash
from bench.can.card import network_toml
from dbm_tools.builder import build_dbm
from dbm_tools.container import data_area
from dbm_tools.network import parse_network
from dbm_tools.parameters import NodeParameterSet
from dpm import flags as fl
from dpm.layout import DEV_FLAGS, HOST_FLAGS, TASK2_STATE
from dpm.task2 import ComDiagnostics, GlobalBits
from firmware.can.bus import BusConfig
from firmware.can.master import Master
from firmware.can.node import NodeHandler
from firmware.device import Device
from firmware.sim import SimulatedNetwork
from tests.conftest import wait_until

BOOT_S = 60.0
"""Time for every node to boot (a loaded machine; a quiet one takes well under a second)."""


def stored(nodes: list[int]) -> bytes:
    """The flash image (data area) of a database of generic nodes."""
    return data_area(build_dbm(parse_network(network_toml(nodes))))


def diagnostics(device: Device) -> ComDiagnostics:
    return ComDiagnostics.decode(bytes(device.mm[TASK2_STATE:TASK2_STATE + 64]))


def counted(monkeypatch: pytest.MonkeyPatch, owner: object, name: str) -> list[int]:
    """Count the calls of ``owner.name`` (a function or a class method), which it still makes."""
    calls: list[int] = []
    real = getattr(owner, name)
    function = getattr(real, "__func__", None)

    def counting(*args: object, **kwargs: object) -> object:
        calls.append(1)
        return real(*args[1:], **kwargs) if function is not None else real(*args, **kwargs)

    monkeypatch.setattr(owner, name, classmethod(counting) if function is not None else counting)
    return calls


@contextmanager
def card_with_nodes(tmp_path: Path, nodes: list[int], others: tuple[int, ...] = ()
                    ) -> Iterator[Device]:
    """A card whose flash holds ``nodes``, powered on beside those nodes and ``others``,
    simulated."""
    channel = f"test-boot-work-{uuid.uuid4().hex}"
    sim = SimulatedNetwork(parse_network(network_toml([*nodes, *others])),
                           can.Bus(interface="virtual", channel=channel))
    device = Device(0, tmp_path, bus=BusConfig("virtual", channel),
                    flash_dir=tmp_path / "flash")
    device.flash.store(stored(nodes))
    loop = threading.Thread(target=device.run, kwargs={"started": sim.start})
    loop.start()
    try:
        yield device
    finally:
        device.stop()
        loop.join(10)
        sim.stop()


def cold_start(device: Device, starts: list[int]) -> None:
    """DevReset(COLDSTART) as a host does it: RESET into DevFlags, a ring; waits for READY
    after the start it caused (``starts``: the calls of ``StoredDatabase.load``)."""
    before = len(starts)
    device.mm[DEV_FLAGS] = fl.RESET
    device.bell.ring_self()
    wait_until(lambda: len(starts) > before and device.mm[HOST_FLAGS] & fl.READY, 10,
               "READY after the cold start")


def all_operating(device: Device, nodes: list[int]) -> None:
    wait_until(lambda: diagnostics(device).operating() == nodes
               and GlobalBits.NEXC not in diagnostics(device).global_bits, BOOT_S,
               f"all {len(nodes)} nodes in Nd_state, NEXC clear")


def test_a_start_from_the_same_flash_checks_and_decodes_no_data_set_again(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """[ours] A cold start that finds in flash the bytes the start before found takes that
    start's verdict and decoded data sets (127 node sets cost each start 30-50 ms of CPU
    before READY, issue 22); one that finds other bytes checks and decodes them, and runs
    what they hold."""
    decoded = counted(monkeypatch, NodeParameterSet, "decode")
    checked = counted(monkeypatch, firmware.flash, "check_dbm")
    starts = counted(monkeypatch, firmware.flash.StoredDatabase, "load")
    nodes = [1, 2, 3]
    with card_with_nodes(tmp_path, nodes, (4, 5)) as device:
        all_operating(device, nodes)
        assert decoded and checked == [1]
        at_power_on = len(decoded)

        cold_start(device, starts)
        all_operating(device, nodes)
        assert len(decoded) == at_power_on, "the same flash was decoded again"
        assert checked == [1], "the same flash was checked again"

        device.flash.store(stored([4, 5]))
        cold_start(device, starts)
        all_operating(device, [4, 5])
        assert checked == [1, 1]
        assert len(decoded) > at_power_on


def test_nexc_costs_a_boot_a_few_looks_per_node(tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """NEXC is set while any node is out of data exchange (seed 4.3), and it is asked after
    every change of a node's state. Asking every node up to the first one missing each time
    made a boot of 127 nodes cost some 15,000 questions (issue 22); the node found missing
    last is asked first, and it stays missing until its own boot-up ends. The bound counts
    the questions NEXC asks of a node's data exchange state (not supervision's, whose
    looks grow with the time a loaded machine takes) over a cold start's boot of 60 nodes."""
    questions: list[int] = []
    exchanging = NodeHandler.exchanging

    def counting(handler: NodeHandler) -> bool:
        if sys._getframe(1).f_globals.get("__name__") == "firmware.can.nmt":
            questions.append(1)
        answer: bool = exchanging.fget(handler)  # type: ignore[attr-defined]
        return answer

    starts = counted(monkeypatch, firmware.flash.StoredDatabase, "load")
    nodes = list(range(1, 61))
    with card_with_nodes(tmp_path, nodes) as device:
        all_operating(device, nodes)
        monkeypatch.setattr(NodeHandler, "exchanging", property(counting))
        cold_start(device, starts)
        all_operating(device, nodes)
        per_node = len(questions) / len(nodes)
        assert per_node <= 15, f"{per_node:.1f} questions of data exchange per node"


def test_a_cold_start_makes_no_thread_event_per_node(tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """Nothing waits on a node's boot-up message (the boot-up is driven by frames), so a
    node's handler keeps it as a flag: a ``threading.Event`` per node (a Condition each, its
    set a notify) cost a start of 127 nodes 3-9 ms before READY (issue 22). Counted over a
    cold start and the boot of 60 nodes: the Events the CAN task's modules make (the
    simulated nodes in this process start threads, each with an Event of its own)."""
    events: list[int] = []

    class CountedEvent(threading.Event):
        def __init__(self) -> None:
            if sys._getframe(1).f_globals.get("__name__", "").startswith("firmware.can."):
                events.append(1)
            super().__init__()

    starts = counted(monkeypatch, firmware.flash.StoredDatabase, "load")
    nodes = list(range(1, 61))
    with card_with_nodes(tmp_path, nodes) as device:
        all_operating(device, nodes)
        monkeypatch.setattr(threading, "Event", CountedEvent)
        cold_start(device, starts)
        all_operating(device, nodes)
        assert len(events) < len(nodes) / 4, f"{len(events)} Events for {len(nodes)} nodes"


def test_a_node_that_boots_does_not_wake_the_master(tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """A node whose boot-up ended in data exchange had the master's thread look at once: a
    boot of 127 nodes woke it once per node (SDO time-outs, the node's tick, NEXC again, the
    outputs: about 100 us each, and the receive thread handing it the interpreter in the
    middle of the boot's frames; issue 22). The master now takes the node at its next look,
    due no later than the node's first deadline. Counted over a cold start and the boot of
    60 nodes: the master's looks."""
    looks = counted(monkeypatch, Master, "_look")
    starts = counted(monkeypatch, firmware.flash.StoredDatabase, "load")
    nodes = list(range(1, 61))
    with card_with_nodes(tmp_path, nodes) as device:
        all_operating(device, nodes)
        before = len(looks)
        cold_start(device, starts)
        all_operating(device, nodes)
        during = len(looks) - before
        assert during < len(nodes) / 2, f"{during} looks of the master for {len(nodes)} nodes"
