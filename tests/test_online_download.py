"""host_api.online.download_data_set against a running card: single and sequenced downloads."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from dbm_tools.parameters import NdFlag, NodeParameterSet, PdoData, SdoCfgData
from dpm.com import UploadRequest
from dpm.commands import COM_DOWNLOAD, COM_END_SEQ, COM_START_SEQ, COM_UPLOAD
from dpm.errors import CanF
from dpm.message import Message
from host_api.board import Board
from host_api.online import ConfigurationError, Transact, board_transact, download_data_set
from tests.conftest import start_card


@pytest.fixture
def board(tmp_path: Path) -> Iterator[Board]:
    network = tmp_path / "network.toml"
    network.write_text("[[node]]\nid = 1\n")
    card = start_card(tmp_path, 0, "--simulate", str(network))
    card_board = Board(0, tmp_path, timeout=5000).open()
    yield card_board
    card_board.close()
    card.stop()


def long_data_set(sdo_entries: int) -> bytes:
    """A valid node parameter data set of 16 + 2 + 9 n + ... bytes (n SDO entries)."""
    sdos = [SdoCfgData(0x2000 + i, 0, 1, bytes([i, 0, 0, 0])) for i in range(sdo_entries)]
    params = NodeParameterSet(bNd_Flag=NdFlag.ACTIVE | NdFlag.HRTBT, usAddTypeInfo=0x000F,
                              usDevProfNum=0x191, usCobIDEmcy=0x81, usCobIDGuard=0x701,
                              usGuardTime=1000, atSdoCfgData=sdos,
                              atPdoCfgData=[PdoData(0, 8, 0x201, 255), PdoData(1, 8, 0x181, 255)],
                              ausInputOffsets=[0], ausOutputOffsets=[0])
    return params.encode()


def recorded(transact: Transact, sent: list[tuple[int, int]]) -> Transact:
    """``transact`` that notes (msg.b, data bytes) of every request."""
    def send(b: int, data: bytes) -> Message:
        sent.append((b, len(data)))
        return transact(b, data)
    return send


def uploaded(board: Board, area: int) -> bytes:
    """The stored data set, read back with COM_Upload in 240-byte pieces."""
    data = b""
    while True:
        answer = board_transact(board)(COM_UPLOAD, UploadRequest(area, 240, len(data)).encode())
        assert answer.f == 0
        data += answer.data
        if len(answer.data) < 240:
            return data


def test_a_short_set_is_one_download(board: Board) -> None:
    raw = long_data_set(0)
    sent: list[tuple[int, int]] = []
    download_data_set(recorded(board_transact(board), sent), 1, raw)
    assert sent == [(COM_DOWNLOAD, 4 + len(raw))]
    assert uploaded(board, 1) == raw


def test_a_long_set_goes_in_the_units_the_card_answers(board: Board) -> None:
    raw = long_data_set(40)
    assert len(raw) > 240
    sent: list[tuple[int, int]] = []
    download_data_set(recorded(board_transact(board), sent), 1, raw)
    assert [b for b, _ in sent] == [COM_START_SEQ, COM_DOWNLOAD, COM_DOWNLOAD, COM_END_SEQ]
    assert sent[1][1] == 4 + 240
    assert uploaded(board, 1) == raw


def test_a_smaller_max_len_data_unit_is_obeyed(board: Board) -> None:
    """The emulated card always answers 240; a card that answers 100 is forced by rewriting
    its COM_Start_Seq answer, the one thing this test cannot get from the real part."""
    transact = board_transact(board)

    def small_unit(b: int, data: bytes) -> Message:
        answer = transact(b, data)
        return replace(answer, data=bytes([100])) if b == COM_START_SEQ else answer

    raw = long_data_set(40)
    sent: list[tuple[int, int]] = []
    download_data_set(recorded(small_unit, sent), 1, raw)
    pieces = [size - 4 for b, size in sent if b == COM_DOWNLOAD]
    assert max(pieces) == 100 and sum(pieces) == len(raw)
    assert uploaded(board, 1) == raw


def test_a_refused_set_raises_with_the_cards_number(board: Board) -> None:
    with pytest.raises(ConfigurationError) as short:
        download_data_set(board_transact(board), 200, b"\0\0", "area 200")
    assert short.value.f == CanF.AREA_CODE
    with pytest.raises(ConfigurationError) as long:
        download_data_set(board_transact(board), 0, long_data_set(40))
    assert long.value.f == CanF.AREA_CODE
    assert "area 0" in str(long.value)
