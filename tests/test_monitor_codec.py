"""The monitor's frame codec on byte vectors: each CANopen service's meaning."""

from __future__ import annotations

from pathlib import Path

import pytest

from dbm_tools.network import load_network
from host_api.monitor.codec import decode
from host_api.network_view import network_view

DATA = Path(__file__).with_name("data")


@pytest.mark.parametrize(
    ("can_id", "data", "kind", "node", "text"),
    [
        (0x000, "0105", "nmt", 5, "NMT start: node 5"),
        (0x000, "8100", "nmt", None, "NMT reset node: all nodes"),
        (0x000, "8207", "nmt", 7, "NMT reset communication: node 7"),
        (0x000, "0203", "nmt", 3, "NMT stop: node 3"),
        (0x000, "8003", "nmt", 3, "NMT enter pre-operational: node 3"),
        (0x080, "", "sync", None, "SYNC"),
        (0x080, "07", "sync", None, "SYNC counter 7"),
        (0x084, "1042090000000000", "emcy", 4,
         "EMCY node 4 4210h Temperature: device temperature, error register 09h"),
        (0x081, "0000000000000000", "emcy", 1, "EMCY node 1 0000h Error Reset / No Error"),
        (0x0A2, "3081110000000000", "emcy", 0x22, "8130h Monitoring: life guard or heartbeat"),
        (0x605, "4000100000000000", "sdo", 5, "SDO upload request node 5 1000h/00h"),
        (0x585, "4300100091010f00", "sdo", 5,
         "SDO upload response node 5 1000h/00h = 91 01 0f 00 (983441)"),
        (0x605, "2b17100064000000", "sdo", 5,
         "SDO download request node 5 1017h/00h = 64 00 (100)"),
        (0x585, "6017100000000000", "sdo", 5, "SDO download response node 5 1017h/00h ok"),
        (0x585, "8000200000000206", "sdo", 5,
         "SDO abort by server node 5 2000h/00h: 06020000h Object does not exist"),
        (0x585, "41081000dc000000", "sdo", 5, "segmented, 220 bytes"),
        (0x585, "0568656c6c6f0000", "sdo", 5, "SDO upload segment node 5 68 65 6c 6c 6f (last)"),
        (0x585, "8000", "sdo", 5, "of 2 bytes (CiA 301 wants 8)"),
        (0x585, "e000000000000000", "sdo", 5, "response node 5 with unknown command specifier 7"),
        (0x605, "c000200000000000", "sdo", 5, "SDO block download request node 5"),
        (0x605, "6000000000000000", "sdo", 5, "SDO upload segment request node 5"),
        (0x705, "00", "heartbeat", 5, "boot-up node 5"),
        (0x705, "05", "heartbeat", 5, "heartbeat node 5 OPERATIONAL"),
        (0x705, "7f", "heartbeat", 5, "heartbeat node 5 PRE-OPERATIONAL"),
        (0x705, "84", "heartbeat", 5, "heartbeat node 5 STOPPED toggle 1"),
        (0x7E5, "5e00000000000000", "lss", None, "LSS request: inquire node-ID"),
        (0x7E4, "5e05000000000000", "lss", None, "LSS response: inquire node-ID"),
        (0x7E5, "0401000000000000", "lss", None, "LSS request: switch state global"),
        (0x185, "0102", "pdo", 5, "TPDO1 node 5"),
        (0x305, "", "pdo", 5, "RPDO2 node 5"),
        (0x100, "000000000000", "time", None, "TIME"),
    ],
)
def test_each_service(can_id: int, data: str, kind: str, node: int | None, text: str) -> None:
    meaning = decode(can_id, bytes.fromhex(data))
    assert (meaning.kind, meaning.node) == (kind, node)
    assert text in meaning.text


def test_remote_frames_extended_and_error_frames() -> None:
    assert decode(0x703, b"", remote=True).text == "guarding request node 3"
    assert decode(0x703, b"", remote=True).kind == "guarding"
    assert decode(0x12345678, b"\x01", extended=True).kind == "other"
    assert decode(0x040, b"", error=True).kind == "error"
    assert decode(0x040, b"", error=True).text == "error frame, class 0x40"
    assert decode(0x181, b"", remote=True).text == "TPDO1 node 1 (RTR)"


def test_pdos_are_named_and_mapped_by_the_network_view(tmp_path: Path) -> None:
    network = tmp_path / "net.toml"
    network.write_text(f'[[node]]\nid = 1\nname = "plain"\n[[node]]\nid = 5\n'
                       f'eds = "{DATA / "io-module.eds"}"\n')
    view = network_view(load_network(network))
    assert view.name(5) == "IO-16/16/2 module" and view.name(1) == "plain"
    analog = decode(0x285, bytes.fromhex("34120100"), view=view)
    assert analog.kind == "pdo" and analog.node == 5
    assert analog.text == ("TPDO2 node 5 in[10..13]: Analogue input 1=0x1234 (4660), "
                           "Analogue input 2=0x1 (1)")
    plain = decode(0x201, bytes(8), view=view)
    assert plain.text == "RPDO1 node 1 out[0..7]"


def test_a_pdo_keeps_the_nodes_own_number_whatever_its_place_in_the_card(tmp_path: Path) -> None:
    """A description lists the PDOs the card maps in any order (here the node's TPDO3, then
    its TPDO1 and TPDO2): each is still named by the node's own number, from the EDS's
    communication object, else from its predefined COB-ID; only a COB-ID of neither kind
    is counted in the list's order."""
    network = tmp_path / "net.toml"
    pdo = '[[node.pdo]]\ndirection = "{}"\ncob_id = {}\nlength = {}\n'
    network.write_text(
        f'[[node]]\nid = 5\neds = "{DATA / "io-module.eds"}"\n'
        + pdo.format("input", "0x385", 4) + pdo.format("input", "0x185", 2)
        + pdo.format("input", "0x285", 4) + pdo.format("output", "0x205", 2)
        + '[[node]]\nid = 1\n' + pdo.format("input", "0x381", 2)
        + pdo.format("input", "0x1F1", 2))
    view = network_view(load_network(network))
    labels = {slot.cob_id: slot.label for slot in view.slots}
    assert labels == {0x385: "TPDO3", 0x185: "TPDO1", 0x285: "TPDO2", 0x205: "RPDO1",
                      0x381: "TPDO3", 0x1F1: "TPDO2"}
    assert decode(0x185, bytes.fromhex("0102"), view=view).text == (
        "TPDO1 node 5 in[8..9]: Read input 1h-8h=0x1 (1), Read input 9h-10h=0x2 (2)")
