"""The card's state as a person reads it: the model and rendering of ``cifemu status``.

It maps the image read-only, so looking never disturbs a running card, and
works on a card whose firmware is down: it then says so (the firmware lock is
free; the last pid) and exits with status 3. It also shows which database the
card's last start loaded from flash.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from rich.console import Group
from rich.table import Table

from dbm_tools.network import NetworkError, load_network
from dpm import flags as fl
from dpm.card_info import read_card_info
from dpm.errors import ERR_NODE_DEVICE, err_event_text
from dpm.flags import DevFlag, HostFlag
from dpm.image import dpm_dir, image_path, open_image
from dpm.layout import image_view
from dpm.task2 import (
    EXCHANGE_MODE_TEXT,
    GLOBAL_BIT_TEXT,
    ComDiagnostics,
    ComPlcParameter,
    GlobalBits,
    node_bits,
)
from host_api.liveness import firmware_liveness
from host_api.network_view import remembered_network


def _bus_text(bus: dict[str, Any]) -> str:
    """The controller's interface and the bit rate in use, against the bus parameters'."""
    where = f"{bus['interface']} channel {bus['channel']}"
    if bus.get("fatal"):
        return f"{where}: FAT, {bus['fatal']}"
    wanted = bus.get("baud_rate")
    if bus.get("sets_bitrate"):
        rate = f"{bus['bitrate']} bit/s" if bus.get("bitrate") else "the interface's own rate"
        return f"{where} at {rate}" + (f" (Baud_rate {wanted} bit/s)" if wanted else "")
    return f"{where}, whose bit rate the card does not set" + (
        f" (Baud_rate {wanted} bit/s)" if wanted else "")


def _text(raw: Any) -> str:
    return bytes(raw).decode("ascii", "replace").strip(" \0")


def error_controls(directory: Path, board: int) -> dict[int, str]:
    """Each node's error control ("heartbeat", "guarding", "none") from the network the card
    was configured from, as configure and the demo note it beside the image; empty when
    none is noted or it no longer loads. The image does not hold it, and Err_Event 30
    reads differently for a heartbeat node (dpm.errors.ERROR_CONTROL_TEXT)."""
    path = remembered_network(directory, board)
    if path is None:
        return {}
    try:
        return {node.id: node.error_control for node in load_network(path).nodes}
    except NetworkError:
        return {}


def snapshot(image: bytes, error_control: Mapping[int, str] | None = None) -> dict[str, Any]:
    """Everything ``status`` shows, decoded from one copy of the image; ``error_control``
    (node -> "heartbeat" or "guarding", see error_controls) words Err_Event 30."""
    view: Any = image_view(bytearray(image))
    host, dev = int(view["HostFlags"]), int(view["DevFlags"])
    rcs, devinfo = view["RcsInfo"], view["DevInfo"]
    diag = ComDiagnostics.decode(bytes(view["Task2State"].tobytes()))
    param = ComPlcParameter.decode(bytes(view["Task2Parameter"].tobytes()))
    driver_type = int(rcs["bDriverType"])
    return {
        "host_flags": [f.name for f in HostFlag if host & f],
        "dev_flags": [f.name for f in DevFlag if dev & f],
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
            "rcs_version": int(rcs["usRcsVersion"]),
            "rcs_error": int(rcs["bRcsError"]),
            "host_watchdog": int(rcs["bHostWatchDog"]),
            "dev_watchdog": int(rcs["bDevWatchDog"]),
            "exchange_mode": driver_type >> 4,
            "exchange_mode_text": EXCHANGE_MODE_TEXT.get(driver_type >> 4, str(driver_type >> 4)),
            "state_mode": driver_type & 0x0F,
        },
        "device": {
            "dpm_size_kib": int(devinfo["bDpmSize"]),
            "dev_identifier": _text(devinfo["abDevIdentifier"]),
            "device_no": int(view["VersionInfo"]["ulDeviceNo"]),
            "serial_no": int(view["VersionInfo"]["ulSerialNo"]),
        },
        "protocol_parameter": {
            "mode": param.bMode,
            "watchdog_time_ms": param.usWatchDogTime,
            "connection_disabled": [n for n in range(128) if n not in node_bits(
                param.abConnStatus)],
        },
        "process_data": {
            "outputs": bytes(view["SndPd"][:32]).hex(),
            "inputs": bytes(view["RcvPd"][:32]).hex(),
        },
        "task2state": {
            "global_bits": [bit.name for bit in GlobalBits if diag.bGlobalBits & bit],
            "can_state": diag.can_state_name,
            "err_node_adr": diag.bErr_rem_adr,
            "err_event": diag.bErr_event,
            "err_text": err_event_text(diag.bErr_rem_adr, diag.bErr_event,
                                       (error_control or {}).get(diag.bErr_rem_adr)),
            "bus_error_cnt": diag.usBus_Error_Cnt,
            "bus_off_cnt": diag.usBus_Off_Cnt,
            "msg_time_out": diag.usMsg_Time_Out,
            "rx_overflow": diag.usRx_Overflow,
            "nd_cfg": diag.configured(),
            "nd_state": diag.operating(),
            "nd_diag": diag.diagnostic(),
        },
    }


def health(directory: Path, board: int) -> dict[str, Any]:
    """Whether the firmware runs (its lock), its (last) pid, and what its last start loaded."""
    live = firmware_liveness(directory, board)
    info = read_card_info(directory, board) or {}
    return {"alive": live.alive, "pid": live.pid, "database": info.get("database"),
            "bus": info.get("bus")}


def _flags_line(names: list[str], every: type[HostFlag] | type[DevFlag]) -> str:
    return " ".join(
        f"[bold green]{f.name}[/]" if f.name in names else f"[dim]{str(f.name).lower()}[/]"
        for f in every
    )


def _database_line(database: dict[str, Any] | None) -> str:
    if database is None:
        return "none in flash (configured on line, or not at all)"
    text = (f"{database['name'] or '(no name)'} of {database['date'] or '?'}, "
            f"{database['nodes']} node(s)")
    return text if database["usable"] else f"{text}, NOT USED: " + "; ".join(database["faults"])


def render(board: int, snap: dict[str, Any]) -> Group:
    """Rich tables of a snapshot (with ``health`` under the key "health" when known)."""
    card = Table(title=f"board {board}", show_header=False, expand=False)
    card.add_column(style="bold")
    card.add_column()
    fw, rcs, dev = snap["firmware"], snap["rcs"], snap["device"]
    state = snap.get("health")
    if state is not None:
        if state["alive"]:
            card.add_row("firmware process", f"running, pid {state['pid']}")
        else:
            last = f"last pid {state['pid']}" if state["pid"] else "stopped cleanly"
            card.add_row("firmware process", f"[bold red]DEAD[/]: the firmware lock is free "
                         f"({last}); the flags below are what it left")
        card.add_row("database", _database_line(state["database"]))
        bus = state["bus"]
        if bus:
            card.add_row("CAN bus", _bus_text(bus))
    card.add_row("HostFlags", _flags_line(snap["host_flags"], HostFlag))
    card.add_row("DevFlags", _flags_line(snap["dev_flags"], DevFlag))
    mbx = snap["mailbox"]
    card.add_row("mailboxes", f"device mailbox {'FULL' if mbx['device_mailbox_full'] else 'free'}, "
                 f"host mailbox {'message waiting' if mbx['host_mailbox_full'] else 'empty'}")
    card.add_row("firmware", f"{fw['name']} {fw['version']}  tasks "
                 + ", ".join(f"{i + 1}:{t}" for i, t in enumerate(fw["tasks"]) if t))
    card.add_row("device", f"{dev['dev_identifier']} {dev['dpm_size_kib']} KiB  "
                 f"device no. {dev['device_no']}  serial {dev['serial_no']:X}")
    card.add_row("RCS", f"version {rcs['rcs_version']:#06x}  error {rcs['rcs_error']}  "
                 f"watchdog host {rcs['host_watchdog']} dev {rcs['dev_watchdog']}")
    card.add_row("process data", f"mode {rcs['exchange_mode_text']}, state field mode "
                 f"{rcs['state_mode']}")
    pp = snap["protocol_parameter"]
    card.add_row("protocol parameter", f"bMode {pp['mode']}  usWatchDogTime "
                 f"{pp['watchdog_time_ms']} ms  stopped nodes "
                 f"{pp['connection_disabled'] or 'none'}")
    card.add_row("outputs 0..31", bytes.fromhex(snap["process_data"]["outputs"]).hex(" "))
    card.add_row("inputs 0..31", bytes.fromhex(snap["process_data"]["inputs"]).hex(" "))
    ts = snap["task2state"]
    diag = Table(title="Task2State (COM_DIAGNOSTICS)", show_header=False)
    diag.add_column(style="bold")
    diag.add_column()
    bits = ts["global_bits"]
    diag.add_row("global bits", "\n".join(GLOBAL_BIT_TEXT[GlobalBits[b]] for b in bits) or "none")
    diag.add_row("CAN_state", ts["can_state"])
    where = "device" if ts["err_node_adr"] == ERR_NODE_DEVICE else f"node {ts['err_node_adr']}"
    diag.add_row("error", f"{ts['err_event']} at {where}: {ts['err_text']}"
                 if ts["err_event"] else "none")
    diag.add_row("counters", f"Bus_Error_Cnt {ts['bus_error_cnt']}  Bus_Off_Cnt "
                 f"{ts['bus_off_cnt']}  Msg_Time_Out {ts['msg_time_out']}  "
                 f"Rx_Overflow {ts['rx_overflow']}")
    for name in ("Nd_cfg", "Nd_state", "Nd_diag"):
        diag.add_row(name, ", ".join(map(str, ts[name.lower()])) or "-")
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
             guarding (or heartbeat) failed, 31 the node left OPERATIONAL, 34 no answer while
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
