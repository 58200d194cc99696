"""``--profile``: py-spy on the firmware during an extra throughput window.

``--profile`` attaches py-spy (``--gil``: only the thread holding the GIL is
sampled) to the firmware for an extra window of phase 2 and adds where the
firmware process spends its time, by thread role, to the document.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

from bench.can.card import (
    SimCard,
    board_of,
)
from bench.can.echo import U64, echo_window

PROFILE_SECONDS = 4.0
PROFILE_RATE = 100


ROLES = {
    "card: CAN master (output changes, RPDO send, supervision)": ("can-master",),
    "card: SYNC producer": ("can-sync",),
    "card: node boot / SDO workers": ("node-boot",),
    "card: device loop (mailboxes, handshakes)": ("MainThread",),
    "card: controller receive (input PDOs -> image)": ("can-receive",),
    "simulator: timers": ("sim scheduler",),
    "simulator: heartbeat producers (python-can cyclic tasks)": ("Cyclic send task",),
}
SIM_RX = "simulator: receive (RPDO apply, echo, TPDO send, SDO server)"


def _py_spy() -> str | None:
    beside = Path(sys.executable).parent / "py-spy"
    return str(beside) if beside.exists() else shutil.which("py-spy")


def profile_window(card: SimCard, values: U64, active: int, out_offset: int,
                   in_offset: int) -> dict[str, Any]:
    """One more throughput window with py-spy sampling the firmware's GIL holder."""
    spy = _py_spy()
    if spy is None:
        return {"error": "py-spy not found"}
    output = card.directory / "profile.txt"
    command = [spy, "record", "--pid", str(card.pid), "--duration", str(int(PROFILE_SECONDS)),
               "--rate", str(PROFILE_RATE), "--format", "raw", "--output", str(output),
               "--threads", "--gil", "--nonblocking"]
    recorder = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    time.sleep(0.3)  # py-spy attaches
    window = echo_window(board_of(card).number, values, active, PROFILE_SECONDS, out_offset,
                         in_offset)
    try:
        _, errors = recorder.communicate(timeout=PROFILE_SECONDS + 30)
    except subprocess.TimeoutExpired:
        recorder.kill()
        _, errors = recorder.communicate()
    if recorder.returncode != 0 or not output.exists():
        return {"error": f"py-spy failed ({recorder.returncode}): "
                         f"{errors.decode(errors='replace').strip()[-300:]}"}
    summary = summarise_profile(output.read_text(), PROFILE_SECONDS * PROFILE_RATE)
    frames = 2 * window.echoes_per_s
    card_busy = summary["card_share"] * summary["gil_busy_fraction"]
    return {
        "tool": f"py-spy record --gil --rate {PROFILE_RATE} --duration {int(PROFILE_SECONDS)}",
        "active_nodes": active,
        "verified_echoes_per_s_while_profiled": round(window.echoes_per_s, 1),
        "lost_while_profiled": window.lost,
        **summary,
        "estimated_card_only_pdo_frames_per_s": round(frames / card_busy, 1)
        if card_busy else None,
        "estimate_note": "frames/s divided by the fraction of wall time the card's own threads "
                         "held the GIL: roughly the rate if the simulated nodes cost nothing "
                         "(rough: the CAN master's cost grows with output changes and nodes, "
                         "not frames)",
    }


def summarise_profile(raw: str, expected_samples: float) -> dict[str, Any]:
    """Shares of GIL samples by thread role and by function (py-spy raw, ``--threads``)."""
    by_thread: Counter[str] = Counter()
    thread_name: dict[str, str] = {}
    inclusive: Counter[str] = Counter()
    total = 0
    for line in raw.splitlines():
        stack, _, count_text = line.rpartition(" ")
        try:
            count = int(count_text)
        except ValueError:
            continue
        frames = stack.split(";")
        head = frames[0]
        tid = head.partition(")")[0]
        thread_name[tid] = head.partition(": ")[2]
        by_thread[tid] += count
        total += count
        seen: set[str] = set()
        for frame in frames[1:]:
            name = frame.split(":")[0] + ")" if ":" in frame else frame
            if name not in seen:
                seen.add(name)
                inclusive[name] += count
    shares: Counter[str] = Counter()
    for tid, count in by_thread.items():
        name = thread_name[tid]
        role = next((r for r, prefixes in ROLES.items() if name.startswith(prefixes)), None)
        if role is None and name.startswith("Notifier"):
            role = SIM_RX  # the card's controller has a receive thread of its own
        shares[role or f"other: {name}"] += count

    def share(value: int) -> float:
        return round(value / total, 3) if total else 0.0

    card = sum(v for k, v in shares.items() if k.startswith("card"))
    sim = sum(v for k, v in shares.items() if k.startswith("simulator"))
    skip = ("Thread._bootstrap", "Thread.run ", "Thread._bootstrap_inner")
    top = [{"function": name, "share": share(value)} for name, value in inclusive.most_common(60)
           if not name.startswith(skip)][:25]
    return {
        "gil_samples": total,
        "gil_busy_fraction": round(min(1.0, total / expected_samples), 3)
        if expected_samples else None,
        "share_by_role": {k: share(v) for k, v in shares.most_common()},
        "card_share": share(card),
        "simulator_share": share(sim),
        "top_functions_inclusive": top,
    }

