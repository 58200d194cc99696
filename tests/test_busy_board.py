"""A board whose mailbox a CiA 309 gateway holds: the others fail at once and name it."""

from __future__ import annotations

import queue
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from dpm.commands import COM_NODE_DIAG
from dpm.errors import Drv
from dpm.message import Message, Task
from host_api.board import Board, CifError
from host_api.download import CONFIGURATION_DOWNLOAD, DevDownload
from host_api.driver import DevCloseDriver, DevExitBoard, DevInitBoard, DevOpenDriver
from tests.conftest import ROOT, start_card


def cifemu(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "cifemu", *args], capture_output=True,
                          text=True, timeout=60, cwd=ROOT)


def test_a_gateway_holding_the_mailbox_is_named_within_a_second(tmp_path: Path) -> None:
    network = tmp_path / "net.toml"
    network.write_text("[[node]]\nid = 2\n")
    dbm = tmp_path / "plant.dbm"
    assert cifemu("dbm", "build", str(network), "-o", str(dbm)).returncode == 0
    card = start_card(tmp_path)
    serve = subprocess.Popen([sys.executable, "-m", "cifemu", "309", "serve", "--dpm-dir",
                              str(tmp_path), "--port", "0"], cwd=ROOT, stderr=subprocess.PIPE,
                             text=True)
    where = ("--dpm-dir", str(tmp_path))
    try:
        assert serve.stderr is not None
        lines: queue.SimpleQueue[str] = queue.SimpleQueue()
        threading.Thread(target=lambda: [lines.put(line) for line in serve.stderr],
                         daemon=True).start()
        match = re.search(r"listening on 127\.0\.0\.1:(\d+)", lines.get(timeout=30))
        assert match is not None
        port = match.group(1)
        # the gateway listens once it holds the board's mailbox (host_api.cia309.link)
        assert DevOpenDriver(tmp_path) == 0 and DevInitBoard(0) == 0
        try:
            started = time.monotonic()
            rc = DevDownload(0, CONFIGURATION_DOWNLOAD, dbm)
            download_s = time.monotonic() - started
        finally:
            DevExitBoard(0)
            DevCloseDriver()
        with Board(0, tmp_path, timeout=5000) as board:
            started = time.monotonic()
            with pytest.raises(CifError) as refused:
                board.transact(Message(rx=Task.CAN, tx=Task.USER, b=COM_NODE_DIAG,
                                       data=bytes([2])))
            transact_s = time.monotonic() - started
        download = cifemu("dbm", "download", str(dbm), *where)
        direct = cifemu("309", "exec", "--direct", "1 read 0x1000 0 u32", *where)
    finally:
        serve.terminate()
        serve.wait(timeout=20)
        card.stop()
    assert rc == Drv.DRV_CMD_ACTIVE and download_s < 1.0
    assert refused.value.code == Drv.DRV_CMD_ACTIVE and transact_s < 1.0
    named = f"(cifemu 309 serve --dpm-dir {tmp_path} --port 0) holds this board's mailbox"
    advice = f"`cifemu 309 exec --port {port} '1 read 0x1000 0 u32'`"
    for text in (str(refused.value), download.stderr, direct.stdout + direct.stderr):
        assert f"the CiA 309 gateway pid {serve.pid} " + named in text, text
        assert advice in text, text
    assert download.returncode == 1 and direct.returncode != 0

