"""Phase 3, ``sdo``: COM_SDO_Up_Download against canopen's SdoClient.

COM_SDO_Up_Download (msg.b 74) of expedited uploads of 1000h, and
download + upload of a 247-byte DOMAIN (the mailbox's largest SDO payload;
segmented, 36 segments each way). The generic node has no DOMAIN, so the
benchmark writes an EDS of the generic node plus DOMAIN 2000h and both sides
simulate that. Baseline: canopen's ``SdoClient`` straight to the node.
Each side is timed by ``bench.common.timed`` in alternating slices.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import canopen
from canopen import objectdictionary as od
from canopen.objectdictionary import ODVariable
from canopen.sdo.exceptions import SdoError

from bench.can.baseline import in_process, sdo_client
from bench.can.card import (
    DEVICE_TYPE_BYTES,
    SimCard,
    board_of,
    configure,
    network_toml,
    simulated_card,
    wait_operating,
)
from bench.common import (
    Rate,
    progress,
    ratio,
    timed,
)
from dbm_tools.network import parse_network
from dpm.commands import COM_NODE_DIAG, COM_SDO_UP_DOWNLOAD, SDO_MAX_DATA
from dpm.message import Message, Task, Tdt, TelegramHeader, Tfc
from firmware.sim.generic import generic_object_dictionary
from host_api.board import CifError

SDO_SECONDS = 2.0
"""Per kind of transfer and side, in SDO_ROUNDS alternating slices."""
SDO_ROUNDS = 4
SDO_WARMUP = 50
DOMAIN_INDEX = 0x2000
DOMAIN_BYTES = SDO_MAX_DATA
"""The largest SDO payload one mailbox message carries (8-byte header + 247 = 255)."""
MAILBOX_SECONDS = 1.0
NODE_DIAG_REQUEST = TelegramHeader(device_adr=1, data_type=Tdt.UINT8, function=Tfc.READ).encode()
"""COM_Node_Diag of node 1."""


def write_bench_eds(directory: Path) -> Path:
    """The generic node's object dictionary plus a read-write DOMAIN 2000h, as an EDS."""
    node = parse_network(network_toml([1])).nodes[0]
    dictionary = generic_object_dictionary(node)
    domain = ODVariable("Benchmark domain", DOMAIN_INDEX, 0)
    domain.data_type = od.DOMAIN
    domain.access_type = "rw"
    dictionary.add_object(domain)
    path = directory / "bench.eds"
    canopen.export_od(dictionary, str(path), doc_type="eds")
    return path


def sdo_message(node: int, index: int, sub: int, data: bytes | None = None) -> Message:
    """COM_SDO_Up_Download: device_adr, index, sub, data_cnt and function read or write."""
    payload = data or b""
    head = TelegramHeader(device_adr=node, data_adr=index, data_idx=sub, data_cnt=len(payload),
                          function=Tfc.WRITE if data is not None else Tfc.READ,
                          payload=payload)
    return Message(rx=Task.CAN, tx=Task.USER, b=COM_SDO_UP_DOWNLOAD, data=head.encode())


DOMAIN_PAYLOAD = bytes(range(DOMAIN_BYTES))


@dataclass(frozen=True, slots=True)
class SdoSteps:
    """One side's transfers, each returning True on success."""

    expedited: Callable[[], bool]
    segmented: Callable[[], bool]


@contextmanager
def card_sdo_steps(eds: Path) -> Iterator[tuple[SdoSteps, Callable[[], bool], SimCard]]:
    """The card's SDO transfers by COM_SDO_Up_Download, and a COM_Node_Diag round trip."""
    text = network_toml([1], eds=eds)
    with simulated_card(text) as card:
        board = board_of(card)
        configure(card, parse_network(text))
        wait_operating(board.number, 1)

        def transact(msg: Message) -> Message | None:
            try:
                return board.transact(msg)
            except CifError:
                return None

        def expedited() -> bool:
            answer = transact(sdo_message(1, 0x1000, 0))
            return answer is not None and answer.f == 0 and answer.data[8:12] == DEVICE_TYPE_BYTES

        def domain() -> bool:
            written = transact(sdo_message(1, DOMAIN_INDEX, 0, DOMAIN_PAYLOAD))
            if written is None or written.f != 0:
                return False
            read = transact(sdo_message(1, DOMAIN_INDEX, 0))
            return read is not None and read.f == 0 and read.data[8:] == DOMAIN_PAYLOAD

        def node_diag() -> bool:
            answer = transact(Message(rx=Task.CAN, tx=Task.USER, b=COM_NODE_DIAG,
                                      data=NODE_DIAG_REQUEST))
            return answer is not None and answer.f == 0

        yield SdoSteps(expedited, domain), node_diag, card


@contextmanager
def baseline_sdo_steps(eds: Path) -> Iterator[SdoSteps]:
    """canopen's SdoClient straight to the same simulated node, in this process."""
    network = parse_network(network_toml([1], eds=eds))
    with in_process(network) as (_, client):
        sdo = sdo_client(client, 1)

        def expedited() -> bool:
            try:
                return bytes(sdo.upload(0x1000, 0)) == DEVICE_TYPE_BYTES
            except SdoError:
                return False

        def domain() -> bool:
            try:
                sdo.download(DOMAIN_INDEX, 0, DOMAIN_PAYLOAD)
                return bytes(sdo.upload(DOMAIN_INDEX, 0)) == DOMAIN_PAYLOAD
            except SdoError:
                return False

        yield SdoSteps(expedited, domain)


def interleaved(card: Callable[[], bool], baseline: Callable[[], bool], warmup: int,
                payload: int, seconds: float = SDO_SECONDS) -> tuple[Rate, Rate]:
    """Card and baseline in alternating slices, so a change of the machine's load hits both;
    ``seconds`` per side in all."""
    slice_s = seconds / SDO_ROUNDS
    totals = (Rate(), Rate())
    for step in (card, baseline):
        for _ in range(warmup):
            step()
    for _ in range(SDO_ROUNDS):
        for total, step in zip(totals, (card, baseline), strict=True):
            part = timed(step, 0, slice_s, payload)
            total.transfers += part.transfers
            total.failures += part.failures
            total.elapsed_s += part.elapsed_s
            total.payload_bytes += part.payload_bytes
    return totals


def sdo() -> dict[str, Any]:
    with (tempfile.TemporaryDirectory(prefix="cifemu-bench-eds-") as tmp,
          card_sdo_steps(write_bench_eds(Path(tmp))) as (card_steps, node_diag, sim_card),
          baseline_sdo_steps(Path(tmp) / "bench.eds") as base_steps):
        progress(f"sdo: expedited uploads, card and baseline alternating, {SDO_ROUNDS} x "
                 f"{SDO_SECONDS / SDO_ROUNDS} s each")
        card_fast, base_fast = interleaved(card_steps.expedited, base_steps.expedited,
                                           SDO_WARMUP, 4)
        progress(f"sdo: {DOMAIN_BYTES}-byte DOMAIN download + upload, alternating")
        card_seg, base_seg = interleaved(card_steps.segmented, base_steps.segmented,
                                         SDO_WARMUP // 5, 2 * DOMAIN_BYTES)
        progress("sdo: COM_Node_Diag mailbox round trips (reference)")
        mailbox = timed(node_diag, SDO_WARMUP, MAILBOX_SECONDS, 0)
        firmware_log = sim_card.log()

    def side(fast: Rate, segmented: Rate) -> dict[str, Any]:
        return {
            "expedited_uploads_per_s": round(fast.per_s(), 1),
            "expedited_failures": fast.failures,
            "segmented_transfers_per_s": round(segmented.per_s(), 1),
            "segmented_kib_per_s": round(segmented.kib_per_s(), 2),
            "segmented_failures": segmented.failures,
        }

    card, baseline = side(card_fast, card_seg), side(base_fast, base_seg)
    card["firmware_log"] = firmware_log
    mailbox_us = 1e6 / mailbox.per_s() if mailbox.per_s() else None
    card["mailbox_reference"] = {
        "name": "COM_Node_Diag (msg.b 66) to the CAN task: the same mailbox round trip, "
                "answered at once by the device loop, no bus traffic",
        "round_trips_per_s": round(mailbox.per_s(), 1),
        "failures": mailbox.failures,
        "us_per_round_trip": round(mailbox_us, 1) if mailbox_us else None,
    }
    if mailbox_us and card_fast.per_s() and base_fast.per_s():
        card["expedited_us_split"] = {
            "total": round(1e6 / card_fast.per_s(), 1),
            "mailbox_round_trip": round(mailbox_us, 1),
            "inside_the_card": round(1e6 / card_fast.per_s() - mailbox_us, 1),
            "baseline_total": round(1e6 / base_fast.per_s(), 1),
            "ceiling_ratio": ratio(1e6 / base_fast.per_s(),
                                   1e6 / base_fast.per_s() + mailbox_us),
            "ceiling_definition": "expedited ratio if the card added only one mailbox round "
                                  "trip to what the baseline's client and node cost",
        }
    return {
        "description": "expedited: upload of 1000h (4 bytes); segmented: download then upload "
                       f"of a {DOMAIN_BYTES}-byte DOMAIN {DOMAIN_INDEX:04X}h (KiB/s counts "
                       "the payload both ways); card: COM_SDO_Up_Download (msg.b 74) by "
                       "Board.transact, one transfer at a time; card and baseline run in "
                       f"{SDO_ROUNDS} alternating slices each",
        "cif": card,
        "baseline": {"name": "canopen SdoClient straight to the same simulated node "
                             "(virtual bus, this process)", **baseline},
        "ratio_to_baseline": {
            "definition": "cif / baseline",
            "expedited": ratio(card["expedited_uploads_per_s"],
                               baseline["expedited_uploads_per_s"]),
            "segmented": ratio(card["segmented_kib_per_s"], baseline["segmented_kib_per_s"]),
        },
    }

