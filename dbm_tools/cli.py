"""The file commands of cifemu dbm: read, check, build and compare DBM files.

File commands (no card needed; FILE is a DBM file or a bare data area such as
a card's flash file database.bin):

  show FILE [--json]          every table, decoded where a codec exists
                              (NODES: header, SDO list, PDO list with the
                              ADD-tab offsets), other tables as hex
  check FILE [--json]         the card's data checks; each finding with the
                              seed manual's error number and text, table,
                              record and field. Exit 1 on errors; warnings
                              (number 0) are shown but exit 0
  build NET.toml -o OUT.dbm   a DBM from a network description and EDS files
  diff A B [--json]           table, record and field differences; exit 1 if any
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from dbm_tools.builder import BuildError, build_dbm
from dbm_tools.container import (
    FILE_MAGIC,
    FIRST_TABLE,
    DbmFile,
    data_area,
    read_data_area,
    read_dbm,
    save_dbm,
    write_dbm,
)
from dbm_tools.errors import DbmError
from dbm_tools.network import BOOT_STEPS, NetworkError, load_network
from dbm_tools.parameters import (
    BAUD_RATES_KBIT,
    BusParameterSet,
    ExtendedBusParameterSet,
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
    checksum_crc,
)
from dbm_tools.validate import Finding, check_dbm

PROG = "cifemu dbm"

DECODERS: dict[str, Callable[[bytes], Any]] = {
    GLOBAL: GlobalSet.decode,
    BUS_CAN: BusParameterSet.decode,
    BUS_CAN_EXT: ExtendedBusParameterSet.decode,
    NODES: NodesRecord.decode,
    PLC_PARAM: PlcParam.decode,
    PROJEKT: ProjektRecord.decode,
    DESCRIPT: DescriptRecord.decode,
}
"""The CANopen tables with a codec; any other table is shown and compared as bytes."""


class UsageError(DbmError):
    """A command that cannot run (unreadable file, no card); the text is for the user."""


# --- reading and decoding ------------------------------------------------------------------


def load_any(path: Path) -> DbmFile:
    """A DBM file, or a bare data area (a card's database.bin, an upload)."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise UsageError(f"cannot read {path}: {exc.strerror}") from None
    try:
        return read_dbm(raw) if raw.startswith(FILE_MAGIC) else read_data_area(raw)
    except DbmError as exc:
        raise UsageError(f"{path} is not a readable DBM: {exc}") from None


def decode(table: str, record: bytes) -> Any:
    """The record's dataclass, or the DbmError why it does not decode; None: no codec."""
    decoder = DECODERS.get(table)
    if decoder is None:
        return None
    try:
        return decoder(record)
    except DbmError as exc:
        return exc


def plain(value: Any) -> Any:
    """JSON-ready: dataclasses as dicts, bytes as hex, tuples as lists."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, bytes | bytearray):
        return bytes(value).hex()
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    return value


def flatten(value: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """(field path, leaf value) pairs of a decoded record, for field-level diffs."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        for f in dataclasses.fields(value):
            yield from flatten(getattr(value, f.name), f"{prefix}.{f.name}" if prefix else f.name)
    elif isinstance(value, list | tuple):
        yield f"{prefix}.count", len(value)
        for index, item in enumerate(value):
            yield from flatten(item, f"{prefix}[{index + 1}]")
    else:
        yield prefix, value


def hex_lines(data: bytes) -> str:
    return "\n".join(
        f"{at:04x}  {data[at : at + 16].hex(' ')}" for at in range(0, len(data), 16)
    ) or "(empty)"


def _show_value(value: Any, field: str) -> str:
    if isinstance(value, bytes):
        return value.hex(" ") or "-"
    if isinstance(value, int) and any(k in field for k in ("COB", "Accept", "CRC")):
        return f"{value:#x}"
    return str(value)


# --- show ----------------------------------------------------------------------------------


def _meaning(table: str, field: str, value: Any, dbm: DbmFile) -> str:
    """A few words where a raw number says little."""
    if table == BUS_CAN and field == "Baud_rate":
        rate = BAUD_RATES_KBIT.get(value)
        return f"{rate} kbit/s" if rate else "unknown code"
    if table == BUS_CAN and field == "SYNC_Timer":
        return "ms, no SYNC" if value == 0 else "ms"
    if table == GLOBAL and field == "bSystemStart":
        return "bus starts when the host clears NOTREADY" if value else "bus starts at once"
    if table == GLOBAL and field == "usChecksumCRC":
        computed = checksum_crc(dbm)
        return "matches the records" if value == computed else f"records give {computed:#06x}"
    if field in ("usHostWatchdogValue", "usWatchDogTime", "usProducerHeartbeatTime"):
        return "ms, 0 = off"
    return ""


def _fields_table(title: str, table: str, record: Any, dbm: DbmFile) -> Table:
    out = Table(title=title, title_justify="left", show_header=False)
    out.add_column(style="bold")
    out.add_column()
    out.add_column(style="dim")
    for f in dataclasses.fields(record):
        value = getattr(record, f.name)
        out.add_row(f.name, _show_value(value, f.name), _meaning(table, f.name, value, dbm))
    return out


def _node_tables(address: int, node: NodeParameterSet) -> list[Table]:
    flags = [flag.name or "" for flag in NdFlag if node.bNd_Flag & flag] or ["inactive"]
    device_type = (node.usAddTypeInfo << 16) | node.usDevProfNum
    skipped = [step for bit, step in enumerate(BOOT_STEPS) if node.bitConfigNdState & (1 << bit)]
    supervision = "heartbeat consumer" if node.bNd_Flag & NdFlag.HRTBT else "guard"
    head = Table(title=f"NODES: node {address}", title_justify="left", show_header=False)
    head.add_column(style="bold")
    head.add_column()
    for name, text in (
        ("bNd_Flag", f"{node.bNd_Flag:#04x} {' '.join(flags)}"),
        ("device type (1000h)", f"{device_type:#010x}: usDevProfNum {node.usDevProfNum}, "
                                f"usAddTypeInfo {node.usAddTypeInfo:#06x}"),
        ("usCobIDEmcy", f"{node.usCobIDEmcy:#x}"),
        ("usCobIDGuard", f"{node.usCobIDGuard:#x}"),
        ("usGuardTime", f"{node.usGuardTime} ms ({supervision} time)"),
        ("bLifeTimeFactor", str(node.bLifeTimeFactor)),
        ("bitConfigNdState", f"{node.bitConfigNdState:#04x} "
                             + (f"skips {', '.join(skipped)}" if skipped else "all boot steps")),
    ):
        head.add_row(name, text)
    tables = [head]
    if node.atSdoCfgData:
        sdo = Table(title=f"node {address}: SDO list", title_justify="left")
        for column in ("#", "index", "sub", "bLength", "value"):
            sdo.add_column(column)
        for index, sdo_entry in enumerate(node.atSdoCfgData, start=1):
            raw = sdo_entry.abSdoValue
            value = int.from_bytes(raw[: max(0, min(sdo_entry.bLength, 4))], "little")
            sdo.add_row(str(index), f"{sdo_entry.usIndex:04X}h", str(sdo_entry.bSubindex),
                        str(sdo_entry.bLength), f"{value:#x} ({raw.hex(' ')})")
        tables.append(sdo)
    pdo = Table(title=f"node {address}: PDO list and ADD-tab", title_justify="left")
    for column in ("#", "direction", "COB-ID", "bytes", "word", "transmission", "inhibit",
                   "offset"):
        pdo.add_column(column)
    offsets = {True: iter(node.ausInputOffsets), False: iter(node.ausOutputOffsets)}
    for index, entry in enumerate(node.atPdoCfgData, start=1):
        offset = next(offsets[entry.is_input], None)
        pdo.add_row(str(index), "input (TX)" if entry.is_input else "output (RX)",
                    f"{entry.usPdoCOBId:#x}", str(entry.data_length),
                    "yes" if entry.word_oriented else "", str(entry.bTransType),
                    str(entry.usInhibitCycle), "missing" if offset is None else str(offset))
    tables.append(pdo)
    extra = [("input", list(offsets[True])), ("output", list(offsets[False]))]
    for what, left in extra:
        if left:
            note = Table(show_header=False, box=None)
            note.add_row(f"[red]ADD-tab: {what} offsets without a PDO: {left}[/]")
            tables.append(note)
    return tables


def _descript_table(records: list[bytes]) -> Table:
    out = Table(title="DESCRIPT", title_justify="left")
    for column in ("station", "ident", "vendor no.", "vendor", "device", "description",
                   "master", "PDOs (flags size@offset)"):
        out.add_column(column)
    for raw in records:
        record = decode(DESCRIPT, raw)
        if isinstance(record, DbmError):
            out.add_row("?", "", "", "", "", f"[red]{record}[/]", "", raw.hex())
            continue
        pdos = ", ".join(f"{p.bFlags:#04x} {p.bSize}@{p.usAddress}" for p in record.atPdos)
        out.add_row(str(record.bStationAddress), f"{record.usIdentNumber:#06x}",
                    f"{record.usVendorNumber:#06x}", record.szVendorName, record.szDeviceName,
                    record.szDescription, str(record.bMasterAddress), pdos or "-")
    return out


def show(path: Path, as_json: bool, console: Console) -> int:
    dbm = load_any(path)
    area = data_area(dbm)
    if as_json:
        document = {
            "file": str(path),
            "date": dbm.date,
            "data_area_bytes": len(area),
            "w0": int.from_bytes(area[:2], "little"),
            "tables": [
                {
                    "number": FIRST_TABLE + 2 * index,
                    "name": table.name,
                    "key_length": table.key_length,
                    "records": [
                        {"bytes": len(record), "hex": record.hex(), "decoded": plain(decoded)}
                        if decoded is not None and not isinstance(decoded, DbmError)
                        else {"bytes": len(record), "hex": record.hex(),
                              **({"error": str(decoded)} if decoded is not None else {})}
                        for record in table.records
                        for decoded in [decode(table.name, record)]
                    ],
                }
                for index, table in enumerate(dbm.tables)
            ],
        }
        print(json.dumps(document, indent=2))
        return 0
    overview = Table(title=f"{path}: DBM of {dbm.date!r}, data area {len(area)} bytes, "
                           f"w0 {int.from_bytes(area[:2], 'little'):#06x}", title_justify="left")
    for column in ("table", "name", "key", "records", "bytes", "codec"):
        overview.add_column(column)
    for index, table in enumerate(dbm.tables):
        overview.add_row(str(FIRST_TABLE + 2 * index), table.name,
                         f"{table.key_length} byte" if table.keyed else "-",
                         str(len(table.records)), str(sum(len(r) for r in table.records)),
                         "yes" if table.name in DECODERS else "hex")
    console.print(overview)
    for table in dbm.tables:
        if table.name == DESCRIPT:
            console.print(_descript_table(table.records))
            continue
        if not table.records:
            console.print(f"[bold]{table.name}[/]: no records")
        for number, record in enumerate(table.records, start=1):
            decoded = decode(table.name, record)
            title = f"{table.name} record {number}"
            if isinstance(decoded, NodesRecord):
                for part in _node_tables(decoded.Node_Address, decoded.Node_Data_set):
                    console.print(part)
            elif decoded is not None and not isinstance(decoded, DbmError):
                console.print(_fields_table(title, table.name, decoded, dbm))
            else:
                note = f" [red](cannot decode: {decoded})[/]" if decoded is not None else ""
                console.print(f"[bold]{title}[/] ({len(record)} bytes){note}")
                console.print(hex_lines(record), highlight=False)
    return 0


# --- check ---------------------------------------------------------------------------------


def _where(finding: Finding, dbm: DbmFile) -> str:
    parts = [
        f"{label} {value}"
        for label, value in (("table", finding.table), ("record", finding.record),
                             ("field", finding.field))
        if value is not None
    ]
    nodes = dbm.table(NODES)
    if finding.table == NODES and finding.record is not None and nodes is not None:
        parts[1] += f" (node {nodes.records[finding.record - 1][0]})"
    return ", ".join(parts) or "database"


def check(path: Path, as_json: bool, console: Console) -> int:
    dbm = load_any(path)
    findings = check_dbm(dbm)
    errors = [f for f in findings if f.severity == "error"]
    if as_json:
        print(json.dumps([
            {"severity": f.severity, "number": f.number, "text": f.text, "table": f.table,
             "record": f.record, "field": f.field, "detail": f.detail}
            for f in findings
        ], indent=2))
        return 1 if errors else 0
    for f in findings:
        if f.severity == "error":
            console.print(f"[red]error {f.number}[/] ({f.text}) in {_where(f, dbm)}: {f.detail}",
                          highlight=False)
        else:
            console.print(f"[yellow]warning[/] in {_where(f, dbm)}: {f.detail}", highlight=False)
    warnings = len(findings) - len(errors)
    verdict = "[red]the card would refuse it[/]" if errors else "[green]the card accepts it[/]"
    console.print(f"{path}: {len(errors)} error(s), {warnings} warning(s): {verdict}")
    return 1 if errors else 0


# --- build ---------------------------------------------------------------------------------


def build(network_path: Path, output: Path, name: str | None, console: Console) -> int:
    try:
        dbm = build_dbm(load_network(network_path), project=name)
    except (NetworkError, BuildError) as exc:
        raise UsageError(f"{network_path}: {exc}") from None
    try:
        save_dbm(output, dbm)
    except OSError as exc:
        raise UsageError(f"cannot write {output}: {exc.strerror}") from None
    nodes = dbm.table(NODES)
    console.print(f"{output}: {len(write_dbm(dbm))} bytes, "
                  f"{len(nodes.records) if nodes else 0} node(s), passes the card's checks")
    for finding in check_dbm(dbm):  # build_dbm refused errors; warnings are the user's call
        console.print(f"[yellow]warning[/]: {finding.detail}", highlight=False)
    return 0


# --- diff ----------------------------------------------------------------------------------


RecordKey = tuple[str, int]
"""How a record is found again in the other file: ("node", 5), ("station", 5) by its key,
("record", 3) by its slot."""


def _records_by_key(dbm: DbmFile, name: str) -> dict[RecordKey, bytes]:
    """Records by their key (NODES: node address; DESCRIPT: station) or their slot."""
    table = dbm.table(name)
    assert table is not None
    if name == DESCRIPT and all(table.records):
        return {("station", r[0]): r for r in table.records}
    if not table.keyed:
        return {("record", n): r for n, r in enumerate(table.records, start=1)}
    label = "node" if name == NODES else "key"
    return {(label, int.from_bytes(r[: table.key_length], "little")): r for r in table.records}


def _record_differences(name: str, a: bytes, b: bytes) -> list[tuple[str, Any, Any]]:
    first, second = decode(name, a), decode(name, b)
    if first is None or isinstance(first, DbmError) or isinstance(second, DbmError):
        at = next((i for i, (x, y) in enumerate(zip(a, b, strict=False)) if x != y),
                  min(len(a), len(b)))
        return [(f"bytes from offset {at}", a[at : at + 16].hex(" ") or "(end)",
                 b[at : at + 16].hex(" ") or "(end)")] + (
            [("length", len(a), len(b))] if len(a) != len(b) else [])
    fields_a, fields_b = dict(flatten(first)), dict(flatten(second))
    return [
        (field, fields_a.get(field, "(absent)"), fields_b.get(field, "(absent)"))
        for field in list(fields_a) + [f for f in fields_b if f not in fields_a]
        if fields_a.get(field) != fields_b.get(field)
    ]


def differences(a: DbmFile, b: DbmFile) -> list[dict[str, Any]]:
    """Every difference as {table, record, record_kind, field, a, b}.

    ``record`` is the record's number (node address, station, key or slot) and
    ``record_kind`` says which; both, like ``field``, are None at table level.
    """
    out: list[dict[str, Any]] = []

    def add(table: str, record: RecordKey | None, field: str | None, left: Any,
            right: Any) -> None:
        kind, number = record if record is not None else (None, None)
        out.append({"table": table, "record": number, "record_kind": kind, "field": field,
                    "a": plain(left), "b": plain(right)})

    names_a, names_b = [t.name for t in a.tables], [t.name for t in b.tables]
    for name in names_a + [n for n in names_b if n not in names_a]:
        if name not in names_b or name not in names_a:
            add(name, None, None, "present" if name in names_a else "absent",
                "present" if name in names_b else "absent")
            continue
        records_a, records_b = _records_by_key(a, name), _records_by_key(b, name)
        for key in list(records_a) + [k for k in records_b if k not in records_a]:
            left, right = records_a.get(key), records_b.get(key)
            if left is None or right is None:
                add(name, key, None, "present" if left is not None else "absent",
                    "present" if right is not None else "absent")
            elif left != right:
                for field, x, y in _record_differences(name, left, right):
                    add(name, key, field, x, y)
    common = [n for n in names_a if n in names_b]
    if common != [n for n in names_b if n in names_a]:
        add("(tables)", None, "order", common, [n for n in names_b if n in names_a])
    return out


def diff(path_a: Path, path_b: Path, as_json: bool, console: Console) -> int:
    found = differences(load_any(path_a), load_any(path_b))
    if as_json:
        print(json.dumps(found, indent=2))
        return 1 if found else 0
    for d in found:
        where = " ".join(str(p) for p in (d["table"], d["record_kind"], d["record"], d["field"])
                         if p is not None)
        console.print(f"{where}: [red]{d['a']}[/] -> [green]{d['b']}[/]", highlight=False)
    console.print(f"{len(found)} difference(s)" if found else "no differences")
    return 1 if found else 0


# --- command line ----------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> argparse._SubParsersAction[Any]:
    """The file commands; returns the subcommands, to which host_api adds the card's."""
    sub = parser.add_subparsers(dest="dbm_command", required=True, metavar="COMMAND")

    p = sub.add_parser("show", help="show every table, decoded where a codec exists",
                       description="Show a DBM file's tables. GLOBAL, BUS_CAN, BUS_CAN_EXT, "
                       "NODES (every node's header, SDO list, PDO list with ADD-tab offsets), "
                       "PLC_PARAM, PROJEKT and DESCRIPT are decoded; other tables are shown "
                       "as hex.")
    p.add_argument("file", type=Path, metavar="FILE", help="a DBM file or a bare data area")
    p.add_argument("--json", action="store_true", help="print every table as JSON")
    p = sub.add_parser("check", help="run the card's data checks (exit 1 on errors)",
                       description="Run the checks the card applies to a stored database. "
                       "Each finding shows the seed manual's error number and text (20 "
                       "database not valid for this device, 53..76 the COM_Download data "
                       "checks, 212 faulty reading of a data base) with its table, record and "
                       "field. Exit status 1 when there are errors; warnings (e.g. a CRC "
                       "SyCon computed differently) are shown and exit 0.")
    p.add_argument("file", type=Path, metavar="FILE", help="a DBM file or a bare data area")
    p.add_argument("--json", action="store_true", help="print the findings as JSON")
    p = sub.add_parser("build", help="build a DBM from a network description",
                       description="Build a DBM from a network description (TOML; see "
                       "dbm_tools.network) and the EDS/DCF files it names. The result passes "
                       "the card's checks, or nothing is written.")
    p.add_argument("network", type=Path, metavar="NETWORK.toml", help="the network description")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="OUT.dbm",
                   help="the DBM file to write")
    p.add_argument("--name", default=None, metavar="PROJECT",
                   help="project name in PROJEKT (default: the network file's name)")
    p = sub.add_parser("diff", help="compare two DBM files (exit 1 if they differ)",
                       description="Compare two DBM files table by table, record by record "
                       "(NODES by node address) and, where a codec exists, field by field. "
                       "Exit status 1 when they differ.")
    p.add_argument("a", type=Path, metavar="A", help="a DBM file or a bare data area")
    p.add_argument("b", type=Path, metavar="B", help="the one to compare it with")
    p.add_argument("--json", action="store_true", help="print the differences as JSON")
    return sub


def dispatch(args: argparse.Namespace, console: Console) -> int:
    """Run one file command: its exit status, or UsageError for the caller to report."""
    command = args.dbm_command
    if command == "show":
        return show(args.file, args.json, console)
    if command == "check":
        return check(args.file, args.json, console)
    if command == "build":
        return build(args.network, args.output, args.name, console)
    return diff(args.a, args.b, args.json, console)

