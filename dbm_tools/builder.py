"""Network description -> DBM: the database a card loads at reset, without SyCon.

``build_dbm(load_network("net.toml"))`` gives the CANopen master's tables in
the order of seed 6.3 (GLOBAL first, as drivers expect it in root slot 8):

- GLOBAL: segment name "CANopen ", bSystemStart from ``[bus] wait_for_host``,
  usHostWatchdogValue from ``host_watchdog_ms``, usChecksumCRC as
  ``tables.checksum_crc`` defines it;
- BUS_CAN, BUS_CAN_EXT: the bus parameter data sets from ``[bus]``;
- NODES: one record per node, keyed by its address, in address order;
- PLC_PARAM: bMode from ``[bus] handshake``, usWatchDogTime = host_watchdog_ms;
- PROJEKT: project name (``--name``, else the file's stem), version, date;
- DESCRIPT: per node its identity (from the EDS) and PDO placement.

A node parameter data set is derived as follows [ours where the seed is silent]:

- bNd_Flag: ACTIVE from ``active``, HRTBT for ``error_control = "heartbeat"``;
- usAddTypeInfo/usDevProfNum: the high/low 16 bits of the expected object
  1000h (seed 5.2.5.1.1: "contents of object 1000H"), from ``device_type``,
  else the EDS, else the generic module's 0x000F0191;
- usGuardTime: the heartbeat consumer time for heartbeat nodes, the guard time
  for guarded nodes, 0 for ``"none"``; bLifeTimeFactor only for guarding;
- SDO list: the description's ``[[node.sdo]]`` entries, plus, for a heartbeat
  node, 1017h (producer heartbeat time) = half the consumer time unless the
  description writes 1017h itself, so that a real node actually produces the
  heartbeat the master supervises;
- PDO list: ``[[node.pdo]]`` when given, else every enabled PDO of the EDS
  (``dbm_tools.eds``), else the generic module's RPDO1 0x200+id and TPDO1
  0x180+id of 8 bytes each;
- process-image offsets: explicit ``offset`` values are kept (overlapping ones
  are an error); the others are placed in node-address order, PDO-list order,
  inputs and outputs separately, each at the lowest offset past the previous
  one that overlaps no explicit area.

DESCRIPT [ours]: ident and vendor numbers are the low 16 bits of the EDS
product code and vendor ID (the record has two bytes for each); names are cut
to 31 characters so that a C host always finds the NUL; PDO lines carry
flags 0x10 (input) / 0x20 (output), the length, data position 0 and the
process-image offset.

The result passes ``check_dbm`` without errors, or ``build_dbm`` raises
``BuildError`` naming the findings: a built database never fails at reset.
"""

from __future__ import annotations

import datetime
import itertools
from dataclasses import dataclass

from dbm_tools.container import DbmFile, DbmTable
from dbm_tools.eds import EdsDevice, EdsError, read_eds
from dbm_tools.errors import DbmError
from dbm_tools.network import (
    GENERIC_DEVICE_TYPE,
    GENERIC_PRODUCT,
    GENERIC_PRODUCT_CODE,
    GENERIC_VENDOR_ID,
    Network,
    NodeDescription,
    PdoDescription,
)
from dbm_tools.parameters import (
    ACLR_ACTIVE,
    ACLR_INACTIVE,
    INTEL,
    MOTOROLA,
    MSK_WORD_PDO,
    BusParameterSet,
    ExtendedBusParameterSet,
    ExtendedState,
    NdFlag,
    NodeParameterSet,
    PdoData,
    SdoCfgData,
)
from dbm_tools.tables import (
    BUS_CAN,
    BUS_CAN_EXT,
    DESCRIPT,
    GLOBAL,
    NODES,
    NODES_KEY_LENGTH,
    PLC_PARAM,
    PROJEKT,
    DescriptPdo,
    DescriptRecord,
    GlobalSet,
    NodesRecord,
    PlcParam,
    ProjektRecord,
    checksum_crc,
)
from dbm_tools.validate import PROCESS_IMAGE_SIZE, check_dbm
from dpm.cia301 import RPDO_BASES, TPDO_BASES
from dpm.cia305 import UNCONFIGURED
from dpm.com import acceptance_long

HEARTBEAT_PRODUCER = 0x1017
DESCRIPT_INPUT = 0x10
DESCRIPT_OUTPUT = 0x20
NAME_LENGTH = 31
PROJECT_NAME_LENGTH = 40
PROJECT_VERSION = "1.000"
DEFAULT_PROJECT = "CANopen network"
GENERIC_VENDOR = "cifemu"
GENERIC_PDO_LENGTH = 8


class BuildError(DbmError, ValueError):
    """A network description that gives no usable database; the message says why."""


@dataclass
class _Node:
    """One node on its way into the tables: its description, data sheet and PDOs."""

    description: NodeDescription
    eds: EdsDevice | None
    pdos: list[PdoDescription]
    offsets: list[int]


def _text(text: str, length: int = NAME_LENGTH) -> str:
    """A name as DESCRIPT and PROJEKT can hold it: Latin-1, NUL-terminated in its field."""
    return text.encode("latin-1", "replace").decode("latin-1").replace("\0", " ")[:length]


def _node_pdos(node: NodeDescription, eds: EdsDevice | None) -> list[PdoDescription]:
    if node.pdo is not None:
        return node.pdo
    if eds is not None:
        return [
            PdoDescription(pdo.direction, pdo.cob_id, pdo.length, pdo.transmission, pdo.inhibit)
            for pdo in eds.pdos
        ]
    return [
        PdoDescription("output", RPDO_BASES[0] + node.id, GENERIC_PDO_LENGTH),
        PdoDescription("input", TPDO_BASES[0] + node.id, GENERIC_PDO_LENGTH),
    ]


def _read_node(node: NodeDescription) -> _Node:
    if node.id == UNCONFIGURED:
        raise BuildError(
            "node 255 (an unconfigured LSS slave) cannot go into a DBM: NODES needs its address"
        )
    try:
        eds = read_eds(node.eds, node.id) if node.eds is not None else None
    except EdsError as exc:
        raise BuildError(f"node {node.id}: {exc}") from exc
    pdos = _node_pdos(node, eds)
    return _Node(node, eds, pdos, [0] * len(pdos))


def _assign_offsets(nodes: list[_Node]) -> None:
    """Fill every node's ``offsets``: explicit ones kept, the rest packed around them."""
    for direction in ("input", "output"):
        wanted = [
            (node, index, pdo)
            for node in nodes
            for index, pdo in enumerate(node.pdos)
            if pdo.direction == direction
        ]
        explicit = sorted(
            ((pdo.offset, pdo.offset + pdo.length, node.description.id, index)
             for node, index, pdo in wanted if pdo.offset is not None),
        )
        for start, end, node_id, index in explicit:
            if end > PROCESS_IMAGE_SIZE:
                raise BuildError(
                    f"node {node_id} PDO {index + 1}: {direction} offset {start} + "
                    f"{end - start} bytes runs past the {PROCESS_IMAGE_SIZE}-byte area"
                )
        for first, second in itertools.pairwise(explicit):
            (start_a, end_a, node_a, index_a), (start_b, end_b, node_b, index_b) = first, second
            if start_b < end_a:
                raise BuildError(
                    f"{direction} areas overlap: node {node_a} PDO {index_a + 1} at "
                    f"{start_a}..{end_a - 1} and node {node_b} PDO {index_b + 1} at "
                    f"{start_b}..{end_b - 1}"
                )
        cursor = 0
        for node, index, pdo in wanted:
            if pdo.offset is not None:
                node.offsets[index] = pdo.offset
                continue
            start = cursor
            for taken_start, taken_end, _, _ in explicit:
                if start < taken_end and taken_start < start + pdo.length:
                    start = taken_end
            if start + pdo.length > PROCESS_IMAGE_SIZE:
                raise BuildError(
                    f"node {node.description.id} PDO {index + 1}: the {direction} area of "
                    f"{PROCESS_IMAGE_SIZE} bytes is full"
                )
            node.offsets[index] = start
            cursor = start + pdo.length


def _device_type(node: _Node) -> int:
    if node.description.device_type is not None:
        return node.description.device_type
    if node.eds is None:
        return GENERIC_DEVICE_TYPE
    if node.eds.device_type is None:
        raise BuildError(
            f"node {node.description.id}: {node.description.eds} has no object 1000h; "
            "give device_type in the description"
        )
    return node.eds.device_type


def _sdo_list(description: NodeDescription) -> list[SdoCfgData]:
    sdos = [
        SdoCfgData(sdo.index, sdo.subindex, sdo.size, sdo.value.to_bytes(4, "little"))
        for sdo in description.sdo
    ]
    writes_producer = any(sdo.index == HEARTBEAT_PRODUCER for sdo in description.sdo)
    if (description.error_control == "heartbeat" and description.heartbeat_ms
            and not writes_producer):
        producer = max(1, description.heartbeat_ms // 2)
        sdos.append(SdoCfgData(HEARTBEAT_PRODUCER, 0, 2, producer.to_bytes(4, "little")))
    return sdos


def _node_set(node: _Node) -> NodeParameterSet:
    description = node.description
    flag = NdFlag(0)
    if description.active:
        flag |= NdFlag.ACTIVE
    if description.error_control == "heartbeat":
        flag |= NdFlag.HRTBT
    guard_time = {
        "heartbeat": description.heartbeat_ms,
        "guarding": description.guard_time_ms,
    }.get(description.error_control, 0)
    life_time = description.life_time_factor if description.error_control == "guarding" else 0
    device_type = _device_type(node)
    pdos = [
        PdoData(
            bTypeOfPdo=1 if pdo.direction == "input" else 0,
            bLength=pdo.length | (MSK_WORD_PDO if pdo.word else 0),
            usPdoCOBId=pdo.cob_id,
            bTransType=pdo.transmission,
            usInhibitCycle=pdo.inhibit,
        )
        for pdo in node.pdos
    ]
    return NodeParameterSet(
        bNd_Flag=int(flag),
        usAddTypeInfo=device_type >> 16,
        usDevProfNum=device_type & 0xFFFF,
        usCobIDEmcy=description.cob_id_emcy,
        usCobIDGuard=description.cob_id_guard,
        usGuardTime=guard_time,
        bLifeTimeFactor=life_time,
        bitConfigNdState=description.config_nd_state,
        atSdoCfgData=_sdo_list(description),
        atPdoCfgData=pdos,
        ausInputOffsets=[
            o for o, p in zip(node.offsets, node.pdos, strict=True) if p.direction == "input"
        ],
        ausOutputOffsets=[
            o for o, p in zip(node.offsets, node.pdos, strict=True) if p.direction == "output"
        ],
    )


def _descript(node: _Node, master_node_id: int) -> DescriptRecord:
    description, eds = node.description, node.eds
    return DescriptRecord(
        bStationAddress=description.id,
        usIdentNumber=(eds.product_number if eds else GENERIC_PRODUCT_CODE) & 0xFFFF,
        usVendorNumber=(eds.vendor_number if eds else GENERIC_VENDOR_ID) & 0xFFFF,
        szVendorName=_text(eds.vendor_name if eds else GENERIC_VENDOR),
        szDeviceName=_text(eds.product_name if eds else GENERIC_PRODUCT),
        szDescription=_text(description.name or f"node {description.id}"),
        bMasterAddress=master_node_id,
        atPdos=[
            DescriptPdo(
                DESCRIPT_INPUT if pdo.direction == "input" else DESCRIPT_OUTPUT,
                pdo.length, 0, offset,
            )
            for pdo, offset in zip(node.pdos, node.offsets, strict=True)
        ],
    )


def build_dbm(
    network: Network, *, project: str | None = None, date: datetime.date | None = None
) -> DbmFile:
    """The DBM of ``network``; ``project`` names it in PROJEKT, ``date`` dates it (today).

    Raises BuildError (with the EDS's or the card's findings) when the description gives
    no database the card would accept.
    """
    bus = network.bus
    nodes = [_read_node(node) for node in sorted(network.nodes, key=lambda n: n.id)]
    _assign_offsets(nodes)
    state = ExtendedState(0)
    if bus.extended_ids:
        state |= ExtendedState.bi11Bit29BitSelector
    if bus.global_start:
        state |= ExtendedState.biNoGobalStartNode
    if project is None:
        project = network.path.stem if network.path is not None else DEFAULT_PROJECT
    when = date or datetime.date.today()
    tables = [
        DbmTable(GLOBAL, [GlobalSet().encode()]),
        DbmTable(BUS_CAN, [BusParameterSet(
            Baud_rate=bus.baud_rate_code,
            COB_ID_SYNC=bus.sync_cob_id,
            SYNC_Timer=bus.sync_period_ms,
            Auto_Clear=ACLR_ACTIVE if bus.auto_clear else ACLR_INACTIVE,
            Intel_Motorola=MOTOROLA if bus.byte_order == "motorola" else INTEL,
        ).encode()]),
        DbmTable(
            NODES,
            [NodesRecord(node.description.id, _node_set(node)).encode() for node in nodes],
            key_length=NODES_KEY_LENGTH,
        ),
        DbmTable(PLC_PARAM, [PlcParam(bus.plc_mode, bus.host_watchdog_ms).encode()]),
        DbmTable(PROJEKT, [ProjektRecord(
            _text(project, PROJECT_NAME_LENGTH), PROJECT_VERSION, when.strftime("%d.%m.%Y")
        ).encode()]),
        DbmTable(DESCRIPT, [_descript(node, bus.master_node_id).encode() for node in nodes]),
        DbmTable(BUS_CAN_EXT, [ExtendedBusParameterSet(
            bExtendedState=int(state),
            ulAcceptCode=acceptance_long(bus.accept_code),
            ulAcceptMask=acceptance_long(bus.accept_mask),
            bNodeID=bus.master_node_id,
            usProducerHeartbeatTime=bus.heartbeat_ms,
        ).encode()]),
    ]
    dbm = DbmFile(tables)
    global_set = GlobalSet(
        bSystemStart=1 if bus.wait_for_host else 0,
        usHostWatchdogValue=bus.host_watchdog_ms,
        usChecksumCRC=checksum_crc(dbm),
    )
    tables[0].records[0] = global_set.encode()
    errors = [f for f in check_dbm(dbm) if f.severity == "error"]
    if errors:
        raise BuildError("the description gives a database the card would refuse:\n" + "\n".join(
            f"  {f.number} ({f.text}): {f.table} record {f.record} {f.field or ''}: {f.detail}"
            for f in errors
        ))
    return dbm
