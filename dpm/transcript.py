"""A session as the host saw it: one decoded line per step, and the diff of two [ours].

The comparison rule (docs/recording.md, "What replay compares"): a transcript has a
line for each message the host put and each answer it got (header and data decoded
with the card's codecs), each process-data exchange that changed a byte of SndPd or
RcvPd, each reset the host asked for and each change of its NOTREADY level. Before an
exchange's line come the card's levels (READY, RUN, COM) and Task2State as the image
held them then, when they differ from the last ones shown: a host exchanges once the
card is in the state it waits for, so these are settled. Left out, because they change
from run to run without a host's doing: time stamps and pids, msg.nr (the host's own
numbering), the handshake bits of the flags, levels and Task2State at answers (the CAN
task's tick and boot threads update them beside the mailbox: an answer may come just
before or just after a node's state changes), Task2State's four counters, exchanges
that changed nothing, and COM_Node_Diag's bNodeState (the state the node's last
heartbeat or guarding answer reported: which one came last is the bus's timing).
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass
from enum import IntEnum, IntFlag

from dpm import flags as fl
from dpm import session as s
from dpm.com import NodeDiagnosis, NodeStatus
from dpm.commands import Com, Plc, Rcs
from dpm.layout import TASK_STATE_SIZE
from dpm.message import Message, MessageError, Task, TelegramHeader
from dpm.task2 import CanState, GlobalBits

LEVELS = fl.READY | fl.RUN | fl.COM
"""HostFlags levels a transcript shows; the rest are handshake bits."""
_UPPER = {"SDO", "NMT", "CAN", "CANMSG", "RX", "TX", "EMCY", "ID", "CFGRX"}
_TELEGRAM = {(Task.PLC, Plc.COM_SHARED_MEMORY), (Task.CAN, Com.SDO_UP_DOWNLOAD),
             (Task.CAN, Com.NODE_DIAG), (Task.CAN, Com.UPLOAD)}
"""Messages whose data start with the extended telegram header."""


_ENUMS: dict[int, type[IntEnum]] = {Task.CAN: Com, Task.PLC: Plc, Task.RCS: Rcs}


@dataclass(frozen=True, slots=True)
class Line:
    """One step: ``head`` names it (``answer COM_SDO_Up_Download node 1``), ``fields``
    are what is compared, in order."""

    head: str
    fields: tuple[tuple[str, str], ...] = ()

    def __str__(self) -> str:
        if not self.fields:
            return self.head
        return f"{self.head}: " + " ".join(f"{k} {v}" for k, v in self.fields)


def command_name(task: int, code: int) -> str:
    """The seed's spelling of a command: COM_SDO_Up_Download, RCS_Load_Function, ..."""
    enum = _ENUMS.get(task)
    try:
        name = enum(code).name if enum is not None else ""
    except ValueError:
        name = ""
    if not name:
        return f"task {task} command {code}"
    words = [w if w in _UPPER else w.capitalize() for w in name.split("_")]
    if enum is Plc:
        return "COM_" + "_".join(words[1:])
    return ("COM_" if enum is Com else "RCS_") + "_".join(words)


def _message_line(kind: str, msg: Message) -> Line:
    task, code = (msg.rx, msg.b) if kind == s.PUT else (msg.tx, msg.a)
    head = f"{kind} {command_name(task, code)}"
    fields: list[tuple[str, str]] = [("f", str(msg.f)), ("e", str(msg.e))]
    data = msg.data
    if (task, code) in _TELEGRAM and len(data) >= TelegramHeader.SIZE:
        try:
            tele = TelegramHeader.decode(data)
        except MessageError:
            tele = None
        if tele is not None:
            head += f" node {tele.device_adr}"
            fields += [("area", str(tele.data_area)), ("adr", f"{tele.data_adr:#x}"),
                       ("idx", str(tele.data_idx)), ("cnt", str(tele.data_cnt)),
                       ("type", str(tele.data_type)), ("function", str(tele.function))]
            data = tele.payload
            if kind == s.ANSWER and code == Com.NODE_DIAG and task == Task.CAN and data:
                fields += _node_diag_fields(data)
                return Line(head, tuple(fields))
    fields.append(("d", data.hex() or "-"))
    return Line(head, tuple(fields))


def _node_diag_fields(data: bytes) -> list[tuple[str, str]]:
    try:
        nd = NodeDiagnosis.decode(data)
    except MessageError:
        return [("d", data.hex())]
    return [("Nodestatus_1", _names(NodeStatus, nd.status)), ("usAddInfo", f"{nd.add_info:#06x}"),
            ("usProfileNumber", str(nd.profile)), ("bActualError", str(nd.actual_error)),
            ("emcy", ",".join(e.hex() for e in nd.emcy) or "-")]


def _nodes(bits: bytes) -> str:
    nodes = [str(n) for n in range(len(bits) * 8) if bits[n >> 3] >> (n & 7) & 1]
    return ",".join(nodes) or "-"


def state_line(state: bytes) -> Line:
    """Task2State without its counters (usBus_Error_Cnt, usBus_Off_Cnt, usMsg_Time_Out,
    usRx_Overflow) and reserved bytes."""
    state = state.ljust(TASK_STATE_SIZE, b"\0")
    try:
        can_state = CanState(state[1]).name
    except ValueError:
        can_state = f"{state[1]:#04x}"
    return Line("Task2State", (
        ("bGlobalBits", _names(GlobalBits, state[0])),
        ("bCAN_State", can_state), ("bErr_rem_adr", str(state[2])),
        ("bErr_event", str(state[3])), ("abNd_cfg", _nodes(state[16:32])),
        ("abNd_state", _nodes(state[32:48])), ("abNd_diag", _nodes(state[48:64]))))


def _names(flags: type[IntFlag], value: int) -> str:
    """``READY|RUN``: the set bits by name (an unnamed bit by its value), 0 for none."""
    named = [member.name or "" for member in flags if value & member]
    rest = value & ~sum(member.value for member in flags)
    return "|".join(named + ([f"{rest:#x}"] if rest else [])) or "0"


def _levels_line(host_flags: int) -> Line:
    return Line("HostFlags", (("levels", _names(fl.HostFlag, host_flags & LEVELS)),))


_RESETS = {fl.RESET: "COLDSTART", fl.INIT: "WARMSTART", fl.RESET | fl.INIT: "BOOTSTART"}


def transcript(records: list[s.Record]) -> list[Line]:
    """The session's steps as the comparison rule keeps them."""
    lines: list[Line] = []
    host_flags = 0
    shown_levels: Line | None = None
    shown_state: Line | None = None
    for record in records:
        kind = record.kind
        if kind == s.HOST_FLAGS:
            host_flags = record.after
            continue
        if kind == s.DEV_FLAGS:
            rising = record.after & ~record.before
            request = _RESETS.get(rising & (fl.RESET | fl.INIT))
            if request is not None:
                parameter = record.parameter.ljust(3, b"\0")
                lines.append(Line(f"reset {request}", (
                    ("bMode", str(parameter[0])),
                    ("usWatchDogTime", str(int.from_bytes(parameter[1:3], "little"))))))
            if (record.before ^ record.after) & fl.NOTREADY:
                lines.append(Line("host not ready" if record.after & fl.NOTREADY
                                  else "host ready"))
            continue
        if kind == s.EXCHANGE:
            levels = _levels_line(host_flags)
            if levels != shown_levels:
                lines.append(levels)
                shown_levels = levels
            if record.state:
                state = state_line(record.state)
                if state != shown_state:
                    lines.append(state)
                    shown_state = state
        if kind in (s.PUT, s.ANSWER):
            lines.append(_message_line(kind, record.msg) if record.msg is not None
                         else Line(f"{kind} none (timed out)"))
        elif kind == s.EXCHANGE and record.changes:
            lines.append(Line("exchange", tuple(
                (f"{area}[{offset}]", data.hex())
                for area in s.AREAS for offset, data in record.changes.get(area, []))))
    return lines


def field_changes(old: Line, new: Line) -> list[str]:
    """``head: field old -> new`` for each field of two lines of the same head."""
    before, after = dict(old.fields), dict(new.fields)
    out = []
    for key in dict.fromkeys([*before, *after]):
        if before.get(key) != after.get(key):
            out.append(f"{old.head}: {key} {before.get(key, '(none)')} -> "
                       f"{after.get(key, '(none)')}")
    return out


def diff(a: list[Line], b: list[Line], name_a: str = "recorded",
         name_b: str = "now") -> list[str]:
    """``diff -u`` of two transcripts, then each changed field of the lines that differ
    only in their fields; empty when the transcripts agree."""
    text_a, text_b = [str(x) for x in a], [str(x) for x in b]
    if text_a == text_b:
        return []
    out = list(difflib.unified_diff(text_a, text_b, name_a, name_b, n=2, lineterm=""))
    fields: list[str] = []
    matcher = difflib.SequenceMatcher(a=text_a, b=text_b, autojunk=False)
    for op, i1, i2, j1, j2 in matcher.get_opcodes():
        if op != "replace":
            continue
        unpaired = list(b[j1:j2])
        for old in a[i1:i2]:  # each line with the next of its head on the other side
            new = next((line for line in unpaired if line.head == old.head), None)
            if new is not None:
                unpaired.remove(new)
                fields += field_changes(old, new)
    if fields:
        out += ["", "changed fields:", *(f"  {line}" for line in fields)]
    return out
