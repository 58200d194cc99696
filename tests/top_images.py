"""A card as `cifemu top`'s model sees it, made by hand: a network with a heartbeat node and
a guarding node, and image bytes with chosen inputs, Err_Event and Nd_state."""

from __future__ import annotations

from pathlib import Path

from dbm_tools.network import load_network
from dpm.layout import DPM_SIZE, RCV_PD, TASK2_STATE
from host_api.network_view import network_view
from host_api.top.model import CardModel

NETWORK = """
[bus]
bitrate = 125000
[[node]]
id = 1
name = "pump"
[[node]]
id = 2
error_control = "guarding"
guard_time_ms = 100
life_time_factor = 2
"""


def model(tmp_path: Path) -> CardModel:
    path = tmp_path / "net.toml"
    path.write_text(NETWORK)
    network = load_network(path)
    return CardModel(view=network_view(network), network=network)


def image(inputs: bytes = b"", err: tuple[int, int] = (0, 0), nd_state: int = 0) -> bytes:
    raw = bytearray(DPM_SIZE)
    raw[RCV_PD : RCV_PD + len(inputs)] = inputs
    raw[TASK2_STATE + 1] = 0xC0  # OPERATE
    raw[TASK2_STATE + 2], raw[TASK2_STATE + 3] = err
    raw[TASK2_STATE + 16] = 0x06  # Nd_cfg: nodes 1, 2
    raw[TASK2_STATE + 32] = nd_state
    return bytes(raw)
