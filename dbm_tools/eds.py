"""What the DBM builder needs from a node's EDS or DCF file, read with the canopen library.

A node parameter data set carries the node's expected device type (object
1000h) and the PDOs the master maps; DESCRIPT carries its identity. All of it
is in the node's electronic data sheet, so the builder takes it from there
instead of asking the user to repeat it in the network description:

- device type: object 1000h (ParameterValue of a DCF, else DefaultValue);
- PDOs: every communication parameter 1400h+n / 1800h+n that has a mapping
  1600h+n / 1A00h+n and whose COB-ID (sub 1) has bit 31 clear; the length is
  the sum of the mapped bit lengths (low byte of each mapping entry) / 8,
  rounded up; COB-IDs written "$NODEID+0x180" are resolved for the node's ID;
  transmission type from sub 2 (255 when absent), inhibit time from sub 3
  (0 when absent, copied unconverted);
- identity: [DeviceInfo] VendorName, VendorNumber, ProductName, ProductNumber,
  falling back to object 1018h subs 1 and 2 for the numbers.

A PDO that maps nothing carries no process data and is left out; one that
maps more than 8 bytes, or uses a 29-bit COB-ID, is an error (the card's
PDO list has neither).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dbm_tools.errors import DbmError

RPDO_COMMUNICATION = 0x1400
RPDO_MAPPING = 0x1600
TPDO_COMMUNICATION = 0x1800
TPDO_MAPPING = 0x1A00
PDO_SLOTS = 512
"""CiA 301: up to 512 RPDOs and 512 TPDOs."""
DEVICE_TYPE = 0x1000
IDENTITY = 0x1018

COB_ID_INVALID = 1 << 31
COB_ID_EXTENDED = 1 << 29
COB_ID_MASK = 0x7FF
MAX_PDO_BYTES = 8
DEFAULT_TRANSMISSION = 255


class EdsError(DbmError, ValueError):
    """An EDS/DCF file the builder cannot use; the message names the file and the object."""


@dataclass(frozen=True)
class EdsPdo:
    """One enabled PDO of the data sheet, seen from the master (input = the node's TPDO)."""

    direction: str
    number: int
    cob_id: int
    length: int
    transmission: int
    inhibit: int


@dataclass(frozen=True)
class EdsDevice:
    """The parts of a data sheet that end up in a DBM."""

    device_type: int | None
    vendor_name: str
    vendor_number: int
    product_name: str
    product_number: int
    pdos: tuple[EdsPdo, ...]


def _value(od: Any, index: int, subindex: int | None = None) -> Any:
    """An entry's value (DCF ParameterValue) or default; None when the entry is absent."""
    if index not in od:
        return None
    entry = od[index]
    if subindex is not None:
        if subindex not in entry:
            return None
        entry = entry[subindex]
    value = entry.value if getattr(entry, "value", None) is not None else entry.default
    return value


def _integer(od: Any, where: Path, index: int, subindex: int | None = None) -> int | None:
    value = _value(od, index, subindex)
    if value is None:
        return None
    if not isinstance(value, int):
        sub = "" if subindex is None else f"sub{subindex}"
        raise EdsError(f"{where}: object {index:04X}h{sub} is not a number: {value!r}")
    return value


def _pdos(od: Any, where: Path) -> list[EdsPdo]:
    pdos = []
    for direction, communication, mapping in (
        ("input", TPDO_COMMUNICATION, TPDO_MAPPING),
        ("output", RPDO_COMMUNICATION, RPDO_MAPPING),
    ):
        for number in range(PDO_SLOTS):
            comm, mapp = communication + number, mapping + number
            if comm not in od or mapp not in od:
                continue
            cob_id = _integer(od, where, comm, 1)
            if cob_id is None or cob_id & COB_ID_INVALID:
                continue
            name = f"{where}: {'TPDO' if direction == 'input' else 'RPDO'}{number + 1}"
            if cob_id & COB_ID_EXTENDED:
                raise EdsError(f"{name} uses a 29-bit COB-ID {cob_id:#x}; the card maps 11-bit")
            count = _integer(od, where, mapp, 0) or 0
            bits = sum((_integer(od, where, mapp, sub) or 0) & 0xFF for sub in range(1, count + 1))
            length = (bits + 7) // 8
            if length == 0:
                continue
            if length > MAX_PDO_BYTES:
                raise EdsError(f"{name} maps {bits} bits, more than {MAX_PDO_BYTES} bytes")
            transmission = _integer(od, where, comm, 2)
            inhibit = _integer(od, where, comm, 3) if direction == "input" else None
            pdos.append(EdsPdo(
                direction, number + 1, cob_id & COB_ID_MASK, length,
                DEFAULT_TRANSMISSION if transmission is None else transmission, inhibit or 0,
            ))
    return pdos


def import_od(path: Path, node_id: int) -> Any:
    """canopen's object dictionary of an EDS/DCF file, with empty [DeviceInfo] entries
    read as absent ([ours]; canopen takes ``int("")`` and fails). CANopenEditor writes
    ``VendorNumber=`` and ``ProductNumber=`` when a project leaves them blank, as in
    CANopenNode's own example DS301_profile.eds. Any error of canopen's parser passes
    through; files of other suffixes go to canopen unchanged."""
    import io

    import canopen  # a quarter of a second: only callers that need an EDS pay it

    if path.suffix.lower() not in (".eds", ".dcf"):
        return canopen.objectdictionary.import_od(str(path), node_id)
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")  # [ours] tools on Windows write their code page
    lines, section = [], ""
    for line in text.splitlines(keepends=True):
        stripped = line.strip()
        if stripped.startswith("["):
            section = stripped.strip("[]").strip().lower()
        elif section == "deviceinfo" and stripped.endswith("=") and "=" not in stripped[:-1]:
            continue
        lines.append(line)
    source = io.StringIO("".join(lines))
    source.name = str(path)
    return canopen.objectdictionary.import_od(source, node_id)


def read_eds(path: Path, node_id: int) -> EdsDevice:
    """Read an EDS/DCF file for node ``node_id`` ($NODEID resolves to it).

    Raises EdsError for a file that cannot be read or that the card cannot map.
    """
    try:
        od = import_od(path, node_id)
    except Exception as exc:
        # The canopen parser lets whatever its input provokes escape (OSError,
        # configparser errors, KeyError, ValueError...); the user needs one message.
        raise EdsError(f"{path}: not a readable EDS/DCF file: {exc}") from exc
    info = od.device_information
    vendor_number = info.vendor_number
    if vendor_number is None:
        vendor_number = _integer(od, path, IDENTITY, 1)
    product_number = info.product_number
    if product_number is None:
        product_number = _integer(od, path, IDENTITY, 2)
    return EdsDevice(
        device_type=_integer(od, path, DEVICE_TYPE),
        vendor_name=info.vendor_name or "",
        vendor_number=vendor_number or 0,
        product_name=info.product_name or "",
        product_number=product_number or 0,
        pdos=tuple(_pdos(od, path)),
    )
