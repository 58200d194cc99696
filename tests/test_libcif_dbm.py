"""dbm_embd.h (seed 6.5) in libcif: the same records as the Python reader, codes for the rest.

The C functions read files the project's builder writes (and the real SyCon file when
$CIFEMU_SYCON_DBM names one) and must return exactly the records dbm_tools' reader
returns; mutated files are fuzzed under AddressSanitizer and UBSan.
"""

from __future__ import annotations

import ctypes
import os
import shutil
import struct
import subprocess
from pathlib import Path

import pytest

from cifemu import libcif
from dbm_tools.builder import build_dbm
from dbm_tools.container import read_dbm, write_dbm
from dbm_tools.network import load_network, parse_network
from tests import commands
from tests.libcif_host import build_libcif, load_libcif

DBM_OK, DBM_NO_DAT, DBM_NO_SET, DBM_DAT_DIR_FULL, DBM_NOT_ENOUGH_FREESPACE, DBM_SET_DEL = range(6)
DEMO = Path(libcif.SOURCE).parent / "cifemu" / "examples" / "demo.toml"
MANY_NODES = "[bus]\nbitrate = 125000\n" + "".join(
    f'[[node]]\nid = {n}\nboot = ["start", "pdo"]\n' for n in range(1, 41))
"""40 nodes: NODES and DESCRIPT need more than SyCon's 30 record slots."""
CC = shutil.which("cc") or shutil.which("gcc")


@pytest.fixture(scope="module")
def lib() -> ctypes.CDLL:
    return load_libcif()


def files() -> dict[str, bytes]:
    found = {
        "two nodes": write_dbm(build_dbm(parse_network(
            "[bus]\nbitrate = 500000\n[[node]]\nid = 3\n[[node]]\nid = 4\n"))),
        "demo": write_dbm(build_dbm(load_network(DEMO))),
        "40 nodes": write_dbm(build_dbm(parse_network(MANY_NODES))),
    }
    sycon = os.environ.get("CIFEMU_SYCON_DBM")
    if sycon:
        found["sycon"] = Path(sycon).read_bytes()
    return found


class Reader:
    """The four seed functions over one buffer, kept alive as long as the reader."""

    def __init__(self, lib: ctypes.CDLL, data: bytes, sized: bool = True) -> None:
        self.lib = lib
        self.buffer = ctypes.create_string_buffer(data, len(data))
        self.rc = (lib.dbm_init_ex(self.buffer, len(data)) if sized
                   else lib.dbm_init(self.buffer))

    def handle(self, name: bytes) -> tuple[int, int]:
        handle = ctypes.c_ubyte()
        return self.lib.dbm_get_num(name, ctypes.byref(handle)), handle.value

    def count(self, handle: int) -> tuple[int, int]:
        number = ctypes.c_ushort()
        return self.lib.dbm_get_num_of_set(handle, ctypes.byref(number)), number.value

    def read(self, handle: int, number: int, room: int = 4096) -> tuple[int, bytes, int]:
        out = ctypes.create_string_buffer(max(1, room))
        length = ctypes.c_ushort(0xFFFF)
        rc = self.lib.dbm_fast_read(handle, number, room, out, ctypes.byref(length))
        return rc, out.raw[: length.value] if rc == DBM_OK else b"", length.value

    def records(self, name: str) -> list[bytes]:
        rc, handle = self.handle(name.encode())
        assert rc == DBM_OK, name
        rc, count = self.count(handle)
        assert rc == DBM_OK
        result = []
        for number in range(1, count + 1):
            rc, record, _ = self.read(handle, number, 0xFFFF)
            assert rc == DBM_OK, (name, number)
            result.append(record)
        return result


@pytest.mark.parametrize("name", list(files()))
def test_the_c_reader_returns_the_python_readers_records(lib: ctypes.CDLL, name: str) -> None:
    data = files()[name]
    dbm = read_dbm(data)
    for reader in (Reader(lib, data), Reader(lib, data, sized=False),
                   Reader(lib, data[44:])):  # the bare data area, as the card stores it
        assert reader.rc == DBM_OK
        for table in dbm.tables:
            assert reader.records(table.name) == table.records, table.name


def test_lookup_codes(lib: ctypes.CDLL) -> None:
    reader = Reader(lib, files()["two nodes"])
    assert reader.handle(b"GLOBAL") == (DBM_OK, 8)
    assert reader.handle(b"NOSUCH")[0] == DBM_NO_DAT
    assert reader.handle(b"GLOBA")[0] == DBM_NO_DAT
    assert reader.handle(b"GLOBALX")[0] == DBM_NO_DAT
    assert lib.dbm_get_num(None, None) == DBM_NO_DAT
    rc, nodes = reader.handle(b"NODES")
    assert reader.count(nodes) == (DBM_OK, 2)
    for bad in (0, 7, 9, 200, 255):
        assert reader.count(bad)[0] == DBM_NO_DAT
        assert reader.read(bad, 1)[0] == DBM_NO_DAT
    assert lib.dbm_get_num_of_set(nodes, None) == DBM_NO_DAT
    assert reader.read(nodes, 0)[0] == DBM_NO_SET
    assert reader.read(nodes, 3)[0] == DBM_NO_SET
    assert reader.read(nodes, 65535)[0] == DBM_NO_SET
    rc, record, length = reader.read(nodes, 1)
    assert rc == DBM_OK and record[0] == 3
    assert reader.read(nodes, 1, length - 1)[::2] == (DBM_NOT_ENOUGH_FREESPACE, length)
    assert reader.read(nodes, 1, length)[0] == DBM_OK


def test_the_header_has_the_seeds_return_codes() -> None:
    header = (libcif.INCLUDE / "dbm_embd.h").read_text()
    names = ["DBM_OK", "DBM_NO_DAT", "DBM_NO_SET", "DBM_DAT_DIR_FULL",
             "DBM_NOT_ENOUGH_FREESPACE", "DBM_SET_DEL"]
    for value, name in enumerate(names):  # seed 6.5: 0 ... 5 in this order
        assert f"#define {name} " in header
        assert header.split(f"#define {name} ")[1].split()[0] == str(value), name


def with_checksum(area: bytearray) -> bytes:
    area[0:2] = struct.pack("<H", sum(struct.unpack(f"<{len(area) // 2 - 1}H", area[2:])) & 0xFFFF)
    return bytes(area)


def test_a_missing_data_set_and_too_many_tables(lib: ctypes.CDLL) -> None:
    data = files()["two nodes"]
    area = bytearray(data[44:])
    reader = Reader(lib, data)
    _, nodes = reader.handle(b"NODES")
    directory = struct.unpack_from("<H", area, 2 * nodes)[0]
    area[2 * directory + 12 + 2 : 2 * directory + 12 + 4] = b"\0\0"  # slot 1 points nowhere
    reader = Reader(lib, with_checksum(area))
    assert reader.rc == DBM_OK
    assert reader.read(nodes, 1)[0] == DBM_SET_DEL
    assert reader.read(nodes, 2)[0] == DBM_OK
    area = bytearray(data[44:])
    area[6:8] = struct.pack("<H", 101)  # w3: more tables than a root has slots
    assert Reader(lib, with_checksum(area)).rc == DBM_DAT_DIR_FULL


@pytest.mark.parametrize("data", [
    b"", b"DBMFILE  \0", bytes(416), b"\xff" * 600,
    b"DBMFILE  \0" + bytes(28) + b"\xff\xff" + bytes(4),  # a header promising 65535 bytes
])
def test_malformed_buffers_give_no_dat(lib: ctypes.CDLL, data: bytes) -> None:
    reader = Reader(lib, data)
    assert reader.rc == DBM_NO_DAT
    assert reader.handle(b"GLOBAL")[0] == DBM_NO_DAT  # nothing stays from the last file
    assert lib.dbm_init_ex(None, 0) == DBM_NO_DAT


def test_a_corrupt_checksum_is_refused(lib: ctypes.CDLL) -> None:
    data = bytearray(files()["two nodes"])
    data[44] ^= 1
    assert Reader(lib, bytes(data)).rc == DBM_NO_DAT


@pytest.mark.skipif(CC is None, reason="no C compiler")
def test_mutated_files_never_crash_under_the_sanitizers(tmp_path: Path) -> None:
    assert CC is not None
    build_libcif("sanitize")
    program = tmp_path / "fuzz_dbm"
    subprocess.run([CC, "-std=c99", "-Wall", "-Wextra", "-Werror", "-g", "-O1",
                    "-fsanitize=address,undefined", "-fno-sanitize-recover=all",
                    str(Path(__file__).with_name("c") / "fuzz_dbm.c"), f"-I{libcif.INCLUDE}",
                    str(libcif.BUILD / "asan" / "libcif.a"), "-pthread", "-o", str(program)],
                   check=True)
    for index, (name, data) in enumerate(files().items()):
        seed = tmp_path / f"{index}.dbm"
        seed.write_bytes(data)
        done = commands.run([str(program), str(seed), "3000", str(index + 1)],
                            capture_output=True, text=True, timeout=300, check=False)
        assert done.returncode == 0, f"{name}:\n{done.stdout}\n{done.stderr}"
        readable = int(done.stdout.split(",")[1].split()[0])
        assert readable > 100, f"{name}: too few mutants got past dbm_init to test the tables"
