"""cifemu status: the card's state as a person reads it.

It maps the image read-only, so looking never disturbs a running card, and
works on a card whose firmware is down (it then says so).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

from rich.console import Console, Group
from rich.live import Live
from rich.table import Table

from dpm import flags as fl
from dpm.errors import ERR_NODE_DEVICE
from dpm.flags import DevFlag, HostFlag
from dpm.image import DEFAULT_DPM_DIR, MAX_DEV_BOARDS, dpm_dir, image_path, open_image
from dpm.layout import image_view
from dpm.task2 import (
    EXCHANGE_MODE_TEXT,
    GLOBAL_BIT_TEXT,
    ComDiagnostics,
    ComPlcParameter,
    GlobalBits,
    node_bits,
)


def _text(raw: Any) -> str:
    return bytes(raw).decode("ascii", "replace").strip(" \0")


def snapshot(image: bytes) -> dict[str, Any]:
    """Everything ``status`` shows, decoded from one copy of the image."""
    view: Any = image_view(bytearray(image))
    host, dev = int(view["HostFlags"]), int(view["DevFlags"])
    rcs, devinfo = view["RcsInfo"], view["DevInfo"]
    diag = ComDiagnostics.decode(bytes(view["Task2State"].tobytes()))
    param = ComPlcParameter.decode(bytes(view["Task2Parameter"].tobytes()))
    driver_type = int(rcs["bDriverType"])
    return {
        "host_flags": {f.name: bool(host & f) for f in HostFlag},
        "dev_flags": {f.name: bool(dev & f) for f in DevFlag},
        "mailbox": {
            "device_mailbox_full": fl.pending(host, dev, fl.DEV_MBX),
            "host_mailbox_full": fl.pending(host, dev, fl.HOST_MBX),
        },
        "firmware": {
            "name": _text(view["FirmwareInfo"]["abFirmwareName"]),
            "version": _text(view["FirmwareInfo"]["abFirmwareVersion"]),
            "tasks": [_text(view["TaskInfo"][i]["abTaskName"]) for i in range(7)],
        },
        "rcs": {
            "usRcsVersion": int(rcs["usRcsVersion"]),
            "bRcsError": int(rcs["bRcsError"]),
            "bHostWatchDog": int(rcs["bHostWatchDog"]),
            "bDevWatchDog": int(rcs["bDevWatchDog"]),
            "exchange_mode": EXCHANGE_MODE_TEXT.get(driver_type >> 4, str(driver_type >> 4)),
            "state_mode": driver_type & 0x0F,
        },
        "device": {
            "bDpmSize": int(devinfo["bDpmSize"]),
            "abDevIdentifier": _text(devinfo["abDevIdentifier"]),
            "ulDeviceNo": int(view["VersionInfo"]["ulDeviceNo"]),
            "ulSerialNo": f"{int(view['VersionInfo']['ulSerialNo']):X}",
        },
        "protocol_parameter": {
            "bMode": param.bMode,
            "usWatchDogTime": param.usWatchDogTime,
            "connection_disabled": [n for n in range(128) if n not in node_bits(
                param.abConnStatus)],
        },
        "process_data": {
            "outputs": bytes(view["SndPd"][:32]).hex(" "),
            "inputs": bytes(view["RcvPd"][:32]).hex(" "),
        },
        "task2state": {
            "global_bits": [bit.name for bit in GlobalBits if diag.bGlobalBits & bit],
            "CAN_state": diag.can_state_name,
            "Err_Node_adr": diag.bErr_rem_adr,
            "Err_Event": diag.bErr_event,
            "Err_text": diag.err_text,
            "Bus_Error_Cnt": diag.usBus_Error_Cnt,
            "Bus_Off_Cnt": diag.usBus_Off_Cnt,
            "Msg_Time_Out": diag.usMsg_Time_Out,
            "Rx_Overflow": diag.usRx_Overflow,
            "Nd_cfg": diag.configured(),
            "Nd_state": diag.operating(),
            "Nd_diag": diag.diagnostic(),
        },
    }


def _flags_line(flags: dict[str, bool]) -> str:
    return " ".join(
        f"[bold green]{k}[/]" if v else f"[dim]{k.lower()}[/]" for k, v in flags.items()
    )


def render(board: int, snap: dict[str, Any]) -> Group:
    """Rich tables of a snapshot."""
    card = Table(title=f"board {board}", show_header=False, expand=False)
    card.add_column(style="bold")
    card.add_column()
    fw, rcs, dev = snap["firmware"], snap["rcs"], snap["device"]
    card.add_row("HostFlags", _flags_line(snap["host_flags"]))
    card.add_row("DevFlags", _flags_line(snap["dev_flags"]))
    mbx = snap["mailbox"]
    card.add_row("mailboxes", f"device mailbox {'FULL' if mbx['device_mailbox_full'] else 'free'}, "
                 f"host mailbox {'message waiting' if mbx['host_mailbox_full'] else 'empty'}")
    card.add_row("firmware", f"{fw['name']} {fw['version']}  tasks "
                 + ", ".join(f"{i + 1}:{t}" for i, t in enumerate(fw["tasks"]) if t))
    card.add_row("device", f"{dev['abDevIdentifier']} {dev['bDpmSize']} KiB  "
                 f"device no. {dev['ulDeviceNo']}  serial {dev['ulSerialNo']}")
    card.add_row("RCS", f"version {rcs['usRcsVersion']:#06x}  error {rcs['bRcsError']}  "
                 f"watchdog host {rcs['bHostWatchDog']} dev {rcs['bDevWatchDog']}")
    card.add_row("process data", f"mode {rcs['exchange_mode']}, state field mode "
                 f"{rcs['state_mode']}")
    pp = snap["protocol_parameter"]
    card.add_row("protocol parameter", f"bMode {pp['bMode']}  usWatchDogTime {pp['usWatchDogTime']}"
                 f" ms  stopped nodes {pp['connection_disabled'] or 'none'}")
    card.add_row("outputs 0..31", snap["process_data"]["outputs"])
    card.add_row("inputs 0..31", snap["process_data"]["inputs"])
    ts = snap["task2state"]
    diag = Table(title="Task2State (COM_DIAGNOSTICS)", show_header=False)
    diag.add_column(style="bold")
    diag.add_column()
    bits = ts["global_bits"]
    diag.add_row("global bits", "\n".join(GLOBAL_BIT_TEXT[GlobalBits[b]] for b in bits) or "none")
    diag.add_row("CAN_state", ts["CAN_state"])
    where = "device" if ts["Err_Node_adr"] == ERR_NODE_DEVICE else f"node {ts['Err_Node_adr']}"
    diag.add_row("error", f"{ts['Err_Event']} at {where}: {ts['Err_text']}"
                 if ts["Err_Event"] else "none")
    diag.add_row("counters", f"Bus_Error_Cnt {ts['Bus_Error_Cnt']}  Bus_Off_Cnt "
                 f"{ts['Bus_Off_Cnt']}  Msg_Time_Out {ts['Msg_Time_Out']}  "
                 f"Rx_Overflow {ts['Rx_Overflow']}")
    for name in ("Nd_cfg", "Nd_state", "Nd_diag"):
        diag.add_row(name, ", ".join(map(str, ts[name])) or "-")
    return Group(card, diag)


def read_image(board: int, directory: str | None) -> bytes | None:
    path = image_path(dpm_dir(directory), board)
    try:
        mm = open_image(path, readonly=True)
    except OSError:
        return None
    try:
        return bytes(mm)
    finally:
        mm.close()


GUIDE = """\
How to read the screen (the card's names, spelt as in its manual and driver):

HostFlags, DevFlags
  The image's last two bytes. HostFlags are written by the card for the host,
  DevFlags by the host for the card. A flag in CAPITALS is set, in lower case
  it is clear.
  READY     the card's firmware is alive (clear while it starts or is down)
  RUN       the card holds a configuration (from its flash or sent on line)
  COM       the card communicates on the bus: the network runs
  NOTREADY  (host) the host is not ready: the card halts the bus, zeroes outputs
  INIT      (host) warm start requested; RESET: cold start requested
  HOSTCOM/HOSTACK   card-to-host mailbox: a message waits while the two differ
  DEVCOM/DEVACK     host-to-card mailbox: full while the two differ
  PDCOM/PDACK       process-data handshake; STATECOM/STATEACK: the state field
  SPCCOM/SPCACK     special control, a level the card mirrors

Task2State, the card's view of the network (one bit per node-ID in Nd_*)
  CAN_state  OFFLINE: not configured, no bus traffic. STOP: configured, but
             the network is halted (host not ready, host watchdog). CLEAR:
             auto-clear stopped every node after one was lost. OPERATE: the
             network runs.
  Nd_cfg     nodes configured in the master (listed by node-ID)
  Nd_state   nodes in data exchange (OPERATIONAL, PDOs flowing) whose guarding
             or heartbeat reports no error; valid only in OPERATE
  Nd_diag    nodes with diagnostics waiting (an error or an EMCY): the host
             reads them with COM_Node_Diag (msg.b 66)
  error      Err_Event at Err_Node_adr (device = the card itself), e.g. 30
             guarding failed, 31 the node left OPERATIONAL, 34 no answer while
             configuring it, 35/36 profile/device type (1000h) differs, 212
             faulty database, 220 host watchdog expired
  global bits  CTRL parameter error, ACLR auto-clear, NEXC a node not in data
             exchange, FAT fatal, EVE bus errors, NRDY host not ready, TOUT a
             frame could not be sent

Common msg.f numbers (the error in a mailbox answer; DevDownload: 1000 + f)
  0 no error            3 SDO abort by the node     17 node does not answer
  19 node still booting 20 no such node configured  21 parameter fault
  54 busy (one SDO per node at a time)              55 faulty parameter
  57 sequence error     60..76 data checks of a configuration
  152 unknown command   200 card not configured (the network does not run)

The full reference: docs/dpm.md sections 1, 2 and 5.
"""
"""The ``--help`` epilog: the card's words explained for a CANopen engineer."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = GUIDE
    parser.add_argument("--board", type=int, default=0, choices=range(MAX_DEV_BOARDS),
                        metavar="N", help="board number 0..3 (default 0)")
    parser.add_argument("--dpm-dir", default=None,
                        help=f"image directory (default $CIF_DPM_DIR or {DEFAULT_DPM_DIR})")
    parser.add_argument("--watch", action="store_true", help="refresh until Ctrl-C")
    parser.add_argument("--interval", type=float, default=0.5, help="--watch refresh seconds")
    parser.add_argument("--json", action="store_true", help="print the decoded state as JSON")


def run(args: argparse.Namespace) -> int:
    console = Console()
    image = read_image(args.board, args.dpm_dir)
    if image is None:
        where = image_path(dpm_dir(args.dpm_dir), args.board)
        print(f"cifemu status: no image at {where}: is `cifemu firmware "
              f"--board {args.board}` running?", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(snapshot(image), indent=2))
        return 0
    if not args.watch:
        console.print(render(args.board, snapshot(image)))
        return 0
    try:
        with Live(render(args.board, snapshot(image)), console=console, auto_refresh=False) as live:
            while True:
                time.sleep(args.interval)
                image = read_image(args.board, args.dpm_dir) or image
                live.update(render(args.board, snapshot(image)), refresh=True)
    except KeyboardInterrupt:
        return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m host_api", description=__doc__)
    add_arguments(parser)
    return run(parser.parse_args(argv))
