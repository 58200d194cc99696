"""libcif's C headers against the card's header (dpm) and the Python driver: no number drifts.

Every ``#define NAME number`` in libcif/include must appear in ``EXPECTED`` below with its
source in dpm (or dbm_tools, host_api.driver for the driver's own constants); a new define
without a source fails the test, so nothing goes unchecked. The structure sizes are compiled
and printed by a real compiler and compared with dpm.layout's dtypes.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from dbm_tools import parameters as prm
from dpm import commands as cmd
from dpm import flags as fl
from dpm import layout
from dpm.com import NodeStatus
from dpm.errors import ERR_NODE_DEVICE, CanF, Drv, PlcF
from dpm.image import MAX_DEV_BOARDS
from dpm.message import TDT_INTEL, Ext, Task, Tdt, Tfc
from dpm.task2 import CanState, PlcMode
from host_api import download as dl
from host_api import driver as drv

ROOT = Path(__file__).resolve().parents[1]
INCLUDE = ROOT / "libcif" / "include"
HEADERS = ["cif_user.h", "rcs_user.h", "rcsdef.h", "com_user.h"]
"""The card's headers: every define in them is checked against dpm."""
OTHER_PROTOCOLS = ["asc_user.h", "nvr_user.h", "dbm_embd.h"]
"""Headers whose numbers are not the card's (other cards' tasks, the seed's DBM codes):
compiled with the others, their numbers checked elsewhere or not the emulator's."""

_BAUD = {f"COM_BAUD_{kbit}": code for code, kbit in prm.BAUD_RATES_KBIT.items()}

EXPECTED: dict[str, int] = {
    **{member.name: int(member) for member in Drv},
    "MAX_DEV_BOARDS": MAX_DEV_BOARDS,
    "COLDSTART": drv.COLDSTART, "WARMSTART": drv.WARMSTART, "BOOTSTART": drv.BOOTSTART,
    "DEVICE_MBX_EMPTY": drv.DEVICE_MBX_EMPTY, "DEVICE_MBX_FULL": drv.DEVICE_MBX_FULL,
    "HOST_MBX_EMPTY": drv.HOST_MBX_EMPTY, "HOST_MBX_FULL": drv.HOST_MBX_FULL,
    "WATCHDOG_STOP": drv.WATCHDOG_STOP, "WATCHDOG_START": drv.WATCHDOG_START,
    "HOST_NOT_READY": drv.HOST_NOT_READY, "HOST_READY": drv.HOST_READY,
    "PARAMETER_READ": drv.PARAMETER_READ, "PARAMETER_WRITE": drv.PARAMETER_WRITE,
    "SPECIAL_CONTROL_CLEAR": drv.SPECIAL_CONTROL_CLEAR,
    "SPECIAL_CONTROL_SET": drv.SPECIAL_CONTROL_SET,
    "FIRMWARE_DOWNLOAD": dl.FIRMWARE_DOWNLOAD, "CONFIGURATION_DOWNLOAD": dl.CONFIGURATION_DOWNLOAD,
    "POLLING_MODE": 0, "INTERRUPT_MODE": 1,  # DevSetOpMode only; no Python counterpart
    **{f"GET_{n}": getattr(drv, f"GET_{n}") for n in (
        "DRIVER_INFO", "VERSION_INFO", "FIRMWARE_INFO", "TASK_INFO", "RCS_INFO", "DEV_INFO",
        "IO_INFO", "IO_SEND_DATA")},
    "STATE_ERR_NON": 0, "STATE_ERR": 1, "STATE_MODE_2": 2,
    "STATE_MODE_3": drv.STATE_MODE_3, "STATE_MODE_4": drv.STATE_MODE_4,
    **{f"FKT_{n}": getattr(drv, f"FKT_{n}") for n in ("OPEN", "CLOSE", "READ", "WRITE", "IO")},
    "STATE_IN": 1, "STATE_WAIT": 2, "STATE_OUT": 3, "STATE_IN_IRQ": 4,
    # rcsdef.h
    "RCS_TASK": Task.RCS, "PLC_TASK": Task.PLC, "MSG_SYSTEM_TX": Task.SYSTEM,
    "RCS_B_SYSFKT": cmd.RCS_SYSTEM_FUNCTION, "RCS_B_LOADFKT": cmd.Rcs.LOAD_FUNCTION,
    "RCS_NAK_MSK": Ext.NAK, "RCS_NORM_MSK": Ext.NORM, "RCS_FIRST_MSK": Ext.FIRST,
    "RCS_CONT_MSK": Ext.CONT, "RCS_LAST_MSK": Ext.LAST, "RCS_SEQ_MSK": Ext.SEQ_MASK,
    "MODE_UPLOAD_DBM": cmd.LoadMode.UPLOAD, "MODE_DOWNLOAD_DBM": cmd.LoadMode.DOWNLOAD,
    "MODE_DEL_FLASH": cmd.LoadMode.DELETE, "MODE_GET_FLASH_DIR": cmd.LoadMode.DIRECTORY,
    # rcs_user.h
    "TASK_F_OK": 0, "TASK_F_MESSAGECOMMAND": PlcF.UNKNOWN_COMMAND,
    "TASK_F_DATA_AREA": PlcF.ILLEGAL_AREA, "TASK_F_DATA_ADR": PlcF.BUFFER_OVERFLOW,
    "TASK_F_DATA_CNT": PlcF.ILLEGAL_COUNT, "TASK_F_DATA_TYPE": PlcF.UNKNOWN_DATA_TYPE,
    "TASK_F_FUNCTION": PlcF.UNKNOWN_FUNCTION, "TASK_F_DEVICE_ADR": PlcF.REMOTE_ADDRESS,
    "TASK_F_NOT_INITIALIZED": CanF.NOT_CONFIGURED,
    "TASK_TFC_READ": Tfc.READ, "TASK_TFC_WRITE": Tfc.WRITE, "TASK_TFC_QUERRY": Tfc.QUERY,
    "TASK_TDT_UINT8": Tdt.UINT8, "TASK_TDT_UINT16": Tdt.UINT16, "TASK_TDT_STRING": Tdt.STRING,
    "TASK_TDT_BIT": Tdt.BIT, "TASK_TDT_IDF_MSK": TDT_INTEL,
    "RCS_SEGMENT_LEN": layout.MSG_STRUC.itemsize, "RCS_MESSAGEHEADER_LEN": layout.MSG_HEADER_SIZE,
    "RCS_TELEGRAMHEADER_LEN": 8,
    # com_user.h
    "COM_TASK_RCS": Task.RCS, "COM_TASK_PLC": Task.PLC, "COM_TASK_CAN": Task.CAN,
    "COM_TASK_USER": Task.USER, "COM_Shared_Memory": cmd.COM_SHARED_MEMORY,
    "COM_Get_Configuration": cmd.GET_CONFIGURATION,
    "COM_Send_CANMsg_Transparent": cmd.COM_SEND_CANMSG_TRANSPARENT,
    "COM_Receive_CANMsg_Transparent": cmd.COM_RECEIVE_TRANSPARENT,
    "COM_Node_Diag": cmd.COM_NODE_DIAG, "COM_Start_Seq": cmd.COM_START_SEQ,
    "COM_Download": cmd.COM_DOWNLOAD, "COM_End_Seq": cmd.COM_END_SEQ,
    "COM_SDO_Up_Download": cmd.COM_SDO_UP_DOWNLOAD, "COM_Upload": cmd.COM_UPLOAD,
    "COM_Reset_Err_Event": cmd.COM_RESET_ERR_EVENT, "COM_CfgRx_Layer2": cmd.COM_CFGRX_LAYER2,
    "COM_Rx_CAN_Layer2": cmd.COM_RX_CAN_LAYER2, "COM_Tx_CAN_Layer2": cmd.COM_TX_CAN_LAYER2,
    "COM_NMT_Module_Protocol": cmd.COM_NMT_MODULE_PROTOCOL,
    "COM_Set_SDO_Timeout": cmd.COM_SET_SDO_TIMEOUT, "COM_Set_Guarding": cmd.COM_SET_GUARDING,
    "COM_Set_Heartbeat_Consumer": cmd.COM_SET_HEARTBEAT_CONSUMER,
    "COM_Set_Emcy_Consumer": cmd.COM_SET_EMCY_CONSUMER,
    "COM_Set_Heartbeat_Producer": cmd.COM_SET_HEARTBEAT_PRODUCER,
    "COM_Set_Node_ID": cmd.COM_SET_NODE_ID, "COM_Bootup_Forwarding": cmd.COM_BOOTUP_FORWARDING,
    "COM_Bootup_Indication": cmd.COM_BOOTUP_INDICATION,
    "COM_AREA_BUS_PARAMETER": cmd.AREA_BUS, "COM_AREA_EXT_BUS_PARAMETER": cmd.AREA_EXTENDED,
    "COM_MAX_LEN_DATA_UNIT": cmd.MAX_LEN_DATA_UNIT, "COM_SDO_MAX_DATA": cmd.SDO_MAX_DATA,
    "NMT_START_REMOTE_NODE": cmd.NMT_START, "NMT_STOP_REMOTE_NODE": cmd.NMT_STOP,
    "NMT_ENTER_PREOPERATIONAL": cmd.NMT_PREOP, "NMT_RESET_NODE": cmd.NMT_RESET_NODE,
    "NMT_RESET_COMMUNICATION": cmd.NMT_RESET_COMM,
    "CANM_SET_MODE_BUFFERED_DEVICE_CONTROLLED": PlcMode.BUFFERED_DEVICE_CONTROLLED,
    "CANM_SET_MODE_UNCONTROLLED": PlcMode.UNCONTROLLED,
    "CANM_SET_MODE_BUFFERED_HOST_CONTROLLED": PlcMode.BUFFERED_HOST_CONTROLLED,
    **{f"CAN_STATE_{s.name}": s for s in CanState},
    "COM_ERR_DEVICE_ADR": ERR_NODE_DEVICE,
    "COM_ND_NO_RESPONSE": NodeStatus.NO_RESPONSE,
    "COM_ND_EMCY_BUFF_OVFL": NodeStatus.EMCY_BUFFER_OVERFLOW,
    "COM_ND_PRM_FAULT": NodeStatus.PRM_FAULT,
    "COM_ND_GUARD_ACTIVE": NodeStatus.GUARD_ACTIVE, "COM_ND_DEACT": NodeStatus.DEACTIVATED,
    **{f"COM_ND_STATE_{s.name}": s for s in cmd.NodeState},
    "COM_ND_FLAG_HRTBT": prm.NdFlag.HRTBT, "COM_ND_FLAG_ACTIVE": prm.NdFlag.ACTIVE,
    **{f"COM_CFG_{f.name}": f for f in prm.ConfigNdState},
    "MSK_LENGTH": prm.MSK_LENGTH, "MSK_WORD_PDO": prm.MSK_WORD_PDO, **_BAUD,
    "ACLR_INACTIVE": prm.ACLR_INACTIVE, "ACLR_ACTIVE": prm.ACLR_ACTIVE,
    "INTEL": prm.INTEL, "MOTOROLA": prm.MOTOROLA,
    "COM_SHM_AREA_BY_FUNCTION": 0, "COM_SHM_AREA_RECEIVE": 1, "COM_SHM_AREA_SEND": 2,
}
"""Header name -> the number the project's Python side uses for it."""

_DEFINE = re.compile(r"^\s*#\s*define\s+(\w+)\s+(-?(?:0[xX][0-9a-fA-F]+|\d+))\b", re.M)


def header_defines() -> dict[str, int]:
    found: dict[str, int] = {}
    for name in HEADERS:
        for key, value in _DEFINE.findall((INCLUDE / name).read_text()):
            number = int(value, 0)
            assert found.get(key, number) == number, f"{key} defined twice differently"
            found[key] = number
    return found


def test_every_define_has_its_source_and_agrees_with_it() -> None:
    defines = header_defines()
    unchecked = set(defines) - set(EXPECTED)
    assert not unchecked, f"defines without a Python source: {sorted(unchecked)}"
    wrong = {k: (v, int(EXPECTED[k])) for k, v in defines.items()
             if k in EXPECTED and v != int(EXPECTED[k])}
    assert not wrong, f"header value, dpm value: {wrong}"


def test_every_installed_header_is_checked_here() -> None:
    present = {path.name for path in INCLUDE.iterdir()}
    assert present == {*HEADERS, *OTHER_PROTOCOLS, "COM_USER.H"}
    assert (INCLUDE / "COM_USER.H").read_text() == (INCLUDE / "com_user.h").read_text()


def test_every_driver_code_is_in_the_header() -> None:
    missing = {m.name for m in Drv} - set(header_defines())
    assert not missing


def test_the_flag_bits_the_driver_uses_are_dpm_flags() -> None:
    """The library names the flags in its source; they must be the bits dpm.flags defines."""
    source = (ROOT / "libcif" / "src" / "dpm.h").read_text()
    for name in ("HOSTCOM", "DEVACK", "PDACK", "STATECOM", "SPCACK", "COM", "RUN", "READY",
                 "HOSTACK", "DEVCOM", "PDCOM", "STATEACK", "SPCCOM", "NOTREADY", "INIT", "RESET"):
        match = re.search(rf"#define\s+FL_{name}\s+(0x[0-9A-Fa-f]+)", source)
        assert match, name
        assert int(match.group(1), 16) == getattr(fl, name), name


def test_the_request_libcif_awaits_no_answer_to_is_dpms() -> None:
    """libcif's ledger skips the request dpm says the card does not answer: the one pair in
    its source is ``dpm.commands.UNANSWERED``, which a second member would make fail."""
    source = (ROOT / "libcif" / "src" / "dpm.h").read_text()
    rx, b = (re.search(rf"#define\s+UNANSWERED_{name}\s+(\d+)", source) for name in ("RX", "B"))
    assert rx and b
    assert {(int(rx.group(1)), int(b.group(1)))} == cmd.UNANSWERED

def _compile_and_run(tmp_path: Path, program: str) -> str:
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler")
    src = tmp_path / "sizes.c"
    src.write_text(program)
    exe = tmp_path / "sizes"
    subprocess.run([cc, "-std=c99", "-Wall", "-Wextra", "-Werror", "-I", str(INCLUDE), str(src),
                    "-o", str(exe)], check=True)
    return subprocess.run([str(exe)], check=True, capture_output=True, text=True).stdout


def test_structures_match_the_image_layout(tmp_path: Path) -> None:
    pairs = {
        "MSG_STRUC": layout.MSG_STRUC, "VERSIONINFO": layout.VERSIONINFO,
        "FIRMWAREINFO": layout.FIRMWAREINFO, "RCSINFO": layout.RCSINFO,
        "DEVINFO": layout.DEVINFO, "COM_DIAGNOSTICS": layout.COM_DIAGNOSTICS,
    }
    offsets = {
        "RCSINFO.bDriverType": ("RcsInfo.bDriverType", "RcsInfo"),
        "RCSINFO.bDevWatchDog": ("RcsInfo.bDevWatchDog", "RcsInfo"),
        "DEVINFO.abDevIdentifier": ("DevInfo.abDevIdentifier", "DevInfo"),
        "COM_DIAGNOSTICS.abNd_cfg": ("Task2State.abNd_cfg", "Task2State"),
        "COM_DIAGNOSTICS.usRx_Overflow": ("Task2State.usRx_Overflow", "Task2State"),
    }
    lines = [f'printf("{n} %u\\n", (unsigned)sizeof({n}));' for n in pairs]
    lines += [f'printf("{k} %u\\n", (unsigned)offsetof({k.split(".")[0]}, {k.split(".")[1]}));'
              for k in offsets]
    program = ("#include <stdio.h>\n#include <stddef.h>\n#include \"cif_user.h\"\n"
               "#include \"com_user.h\"\nint main(void) {\n" + "\n".join(lines)
               + "\nreturn 0;\n}\n")
    out = dict(line.split() for line in _compile_and_run(tmp_path, program).splitlines())
    for name, dtype in pairs.items():
        assert int(out[name]) == dtype.itemsize, name
    for key, (field, parent) in offsets.items():
        assert int(out[key]) == layout.offset_of(field) - layout.offset_of(parent), key
    assert int(out["DEVINFO.abDevIdentifier"]) == 3


def test_headers_compile_as_c89_c11_and_cpp(tmp_path: Path) -> None:
    """The size assertions hold in every dialect (each one fails compilation otherwise)."""
    src = tmp_path / "all.c"
    src.write_text("".join(f'#include "{h}"\n' for h in [*HEADERS, *OTHER_PROTOCOLS, "COM_USER.H"])
                   + "int main(void){return 0;}\n")
    for compiler, flags in (("cc", ["-std=c89", "-Wno-long-long"]), ("cc", ["-std=c11"]),
                            ("c++", ["-x", "c++", "-std=c++11"])):
        exe = shutil.which(compiler)
        if exe is None:
            continue
        subprocess.run([exe, *flags, "-Wall", "-Wextra", "-Werror", "-I", str(INCLUDE), str(src),
                        "-o", str(tmp_path / "all")], check=True)


def test_the_image_offsets_the_library_uses_are_dpm_layout_offsets() -> None:
    source = (ROOT / "libcif" / "src" / "dpm.h").read_text()
    fields = {
        "SND_PD": "SndPd", "RCV_PD": "RcvPd", "DEV_MBX": "DevMbx", "VERSION_INFO": "VersionInfo",
        "PC_MBX": "PcMbx", "FIRMWARE_INFO": "FirmwareInfo", "TASK1_PARAMETER": "Task1Parameter",
        "TASK2_PARAMETER": "Task2Parameter", "TASK1_STATE": "Task1State",
        "TASK2_STATE": "Task2State", "TASK_INFO": "TaskInfo", "RCS_INFO": "RcsInfo",
        "RCS_ERROR": "RcsInfo.bRcsError", "HOST_WATCHDOG": "RcsInfo.bHostWatchDog",
        "DEV_WATCHDOG": "RcsInfo.bDevWatchDog", "DRIVER_TYPE": "RcsInfo.bDriverType",
        "DEV_INFO": "DevInfo", "DPM_SIZE": "DevInfo.bDpmSize",
        "DEV_IDENTIFIER": "DevInfo.abDevIdentifier", "HOST_FLAGS": "HostFlags",
        "DEV_FLAGS": "DevFlags",
    }
    found = {name: int(value, 16)
             for name, value in re.findall(r"#define\s+OFS_(\w+)\s+(0x[0-9A-Fa-f]+)", source)}
    assert set(found) == set(fields)
    for name, field in fields.items():
        assert found[name] == layout.offset_of(field), name
    sizes = dict(re.findall(r"#define\s+(DPM_SIZE|IO_AREA_SIZE|LAST_KB)\s+(\w+)", source))
    assert int(sizes["DPM_SIZE"], 0) == layout.DPM_SIZE
    assert int(sizes["IO_AREA_SIZE"], 0) == layout.IO_AREA_SIZE
    assert int(sizes["LAST_KB"], 0) == layout.LAST_KB
