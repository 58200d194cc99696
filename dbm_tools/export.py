"""DBM -> network description: a SyCon project's database as the TOML ``cifemu`` reads.

``export_network(dbm)`` is the inverse of ``builder.build_dbm`` for everything the card
uses: the bus parameters (BUS_CAN, BUS_CAN_EXT), the start-up fields (GLOBAL,
PLC_PARAM) and each node's parameter data set (NODES: device type, supervision,
COB-IDs, boot steps, SDO list, PDOs with their process-image offsets). Built again, the
description gives the same BUS_CAN, BUS_CAN_EXT, NODES, GLOBAL and PLC_PARAM records,
so a database can be simulated (``cifemu sim``) without rewriting it by hand.

What a description cannot carry goes into comments at the top [ours]: the PROJEKT
record (give its name to ``cifemu dbm build --name``) and DESCRIPT's vendor and device
names, which the builder takes from an EDS file (``eds = ...``); the node names come
from DESCRIPT's descriptions. Every value is written explicitly, offsets and COB-IDs
included, so a later change of the builder's defaults cannot move them.
"""

from __future__ import annotations

import json

from dbm_tools.container import DbmFile
from dbm_tools.errors import DbmError
from dbm_tools.network import BITRATES, BOOT_STEPS, HANDSHAKES
from dbm_tools.parameters import (
    ACLR_ACTIVE,
    MOTOROLA,
    BusParameterSet,
    ExtendedBusParameterSet,
    ExtendedState,
    NdFlag,
    NodeParameterSet,
)
from dbm_tools.tables import (
    BUS_CAN,
    BUS_CAN_EXT,
    DESCRIPT,
    GLOBAL,
    NODES,
    PLC_PARAM,
    PROJEKT,
    DescriptRecord,
    GlobalSet,
    NodesRecord,
    PlcParam,
    ProjektRecord,
)
from dpm.com import acceptance_identifier_bits

_BITRATE_OF_CODE = {code: rate for rate, code in BITRATES.items()}
_HANDSHAKE_OF_MODE = {mode: name for name, mode in HANDSHAKES.items()}


def _string(text: str) -> str:
    """A TOML basic string (JSON's escapes are TOML's)."""
    return json.dumps(text, ensure_ascii=False)


def _record(dbm: DbmFile, name: str) -> bytes | None:
    table = dbm.table(name)
    return table.records[0] if table is not None and table.records else None


def _bus_lines(dbm: DbmFile) -> list[str]:
    raw = _record(dbm, BUS_CAN)
    if raw is None:
        raise DbmError("no BUS_CAN table: not a CANopen master database", field="BUS_CAN")
    bus = BusParameterSet.decode(raw)
    if bus.Baud_rate not in _BITRATE_OF_CODE:
        raise DbmError(f"Baud_rate {bus.Baud_rate} is none of the card's", field="Baud_rate")
    lines = ["[bus]", f"bitrate = {_BITRATE_OF_CODE[bus.Baud_rate]}",
             f"sync_cob_id = {bus.COB_ID_SYNC:#05x}", f"sync_period_ms = {bus.SYNC_Timer}",
             f"auto_clear = {str(bus.Auto_Clear == ACLR_ACTIVE).lower()}",
             f"byte_order = {_string('motorola' if bus.Intel_Motorola == MOTOROLA else 'intel')}"]
    raw = _record(dbm, BUS_CAN_EXT)
    if raw is not None:
        ext = ExtendedBusParameterSet.decode(raw)
        state = ExtendedState(ext.bExtendedState)
        lines += [f"master_node_id = {ext.bNodeID}",
                  f"heartbeat_ms = {ext.usProducerHeartbeatTime}",
                  f"global_start = {str(ExtendedState.biNoGobalStartNode in state).lower()}",
                  f"accept_code = {acceptance_identifier_bits(ext.ulAcceptCode):#x}",
                  f"accept_mask = {acceptance_identifier_bits(ext.ulAcceptMask):#x}",
                  f"extended_ids = {str(ExtendedState.bi11Bit29BitSelector in state).lower()}"]
    raw = _record(dbm, GLOBAL)
    if raw is not None:
        start = GlobalSet.decode(raw)
        lines += [f"wait_for_host = {str(bool(start.bSystemStart)).lower()}",
                  f"host_watchdog_ms = {start.usHostWatchdogValue}"]
    raw = _record(dbm, PLC_PARAM)
    if raw is not None and PlcParam.decode(raw).bMode in _HANDSHAKE_OF_MODE:
        lines.append(f"handshake = {_string(_HANDSHAKE_OF_MODE[PlcParam.decode(raw).bMode])}")
    return lines


def _supervision(node: NodeParameterSet) -> list[str]:
    if node.bNd_Flag & NdFlag.HRTBT:
        return ['error_control = "heartbeat"', f"heartbeat_ms = {node.usGuardTime}"]
    if node.usGuardTime or node.bLifeTimeFactor:
        return ['error_control = "guarding"', f"guard_time_ms = {node.usGuardTime}",
                f"life_time_factor = {node.bLifeTimeFactor}"]
    return ['error_control = "none"']


def _node_lines(address: int, node: NodeParameterSet, descript: DescriptRecord | None
                ) -> list[str]:
    lines = ["[[node]]", f"id = {address}"]
    if descript is not None and descript.szDescription != f"node {address}":
        lines.append(f"name = {_string(descript.szDescription)}")
    lines += [f"active = {str(node.active).lower()}", *_supervision(node),
              f"emcy_cob_id = {node.usCobIDEmcy:#05x}", f"guard_cob_id = {node.usCobIDGuard:#05x}",
              f"device_type = {(node.usAddTypeInfo << 16) | node.usDevProfNum:#010x}"]
    if node.bitConfigNdState:
        steps = [s for bit, s in enumerate(BOOT_STEPS) if not node.bitConfigNdState >> bit & 1]
        lines.append(f"boot = [{', '.join(_string(s) for s in steps)}]")
    for sdo in node.atSdoCfgData:
        lines += ["[[node.sdo]]", f"index = {sdo.usIndex:#06x}", f"subindex = {sdo.bSubindex}",
                  f"value = {int.from_bytes(sdo.abSdoValue, 'little'):#x}",
                  f"size = {sdo.bLength}"]
    offsets = {True: iter(node.ausInputOffsets), False: iter(node.ausOutputOffsets)}
    for pdo in node.atPdoCfgData:
        lines += ["[[node.pdo]]", f"direction = {_string('input' if pdo.is_input else 'output')}",
                  f"cob_id = {pdo.usPdoCOBId:#05x}", f"length = {pdo.data_length}",
                  f"transmission = {pdo.bTransType}", f"inhibit = {pdo.usInhibitCycle}"]
        if pdo.word_oriented:
            lines.append("word = true")
        offset = next(offsets[pdo.is_input], None)
        if offset is not None:
            lines.append(f"offset = {offset}")
    return lines


def _header(dbm: DbmFile, source: str, descripts: dict[int, DescriptRecord]) -> list[str]:
    lines = [f"# Exported from {source} by `cifemu dbm export`."]
    raw = _record(dbm, PROJEKT)
    if raw is not None:
        project = ProjektRecord.decode(raw)
        lines.append(f"# PROJEKT: {project.szProjectName!r}, version {project.szVersion!r}, "
                     f"{project.szDate}; to keep its name: cifemu dbm build THIS.toml "
                     f"-o OUT.dbm --name {_string(project.szProjectName)}")
    for address, record in sorted(descripts.items()):
        lines.append(f"# node {address}: {record.szVendorName} {record.szDeviceName} "
                     f"(vendor {record.usVendorNumber:#06x}, ident {record.usIdentNumber:#06x})"
                     "; give eds = ... to keep DESCRIPT's identity")
    return lines


def export_network(dbm: DbmFile, source: str = "a DBM") -> str:
    """The network description of ``dbm``, as TOML text; raises DbmError for a database
    that is no CANopen master's (no BUS_CAN) or whose records do not decode."""
    table = dbm.table(DESCRIPT)
    records = [DescriptRecord.decode(raw) for raw in (table.records if table else [])]
    descripts = {record.bStationAddress: record for record in records}
    lines = [*_header(dbm, source, descripts), "", *_bus_lines(dbm)]
    nodes = dbm.table(NODES)
    for raw in nodes.records if nodes is not None else []:
        record = NodesRecord.decode(raw)
        lines += ["", *_node_lines(record.Node_Address, record.Node_Data_set,
                                   descripts.get(record.Node_Address))]
    return "\n".join(lines) + "\n"
