"""cifemu record: attach to a running card and record a session until Ctrl-C [ours].

    cifemu record --board N -o SESSION [--seconds S] [--dpm-dir DIR]

Records what `cifemu firmware --record` records from the start, from now on: every
mailbox message in both directions with the pid of its host, every change of the host
and device flags, every process-data exchange, every CAN frame (SESSION/can.log, in
candump's log format). It ends on Ctrl-C, SIGTERM, after --seconds, or when the card
stops; the session is complete when the command has printed its summary. Replay it
with `cifemu replay SESSION`. This command creates SESSION and its files as its own
user and hands the open files to the card, which never opens a path of yours; the
image directory's permissions decide who may attach (docs/security.md). One recording
at a time per card. docs/recording.md describes the session.
"""

from __future__ import annotations

import argparse
import select
import signal
import sys
import time
from pathlib import Path
from types import FrameType

from dpm.image import DEFAULT_DPM_DIR, MAX_DEV_BOARDS, dpm_dir, image_path
from dpm.record_socket import RecordingError, Summary, attach

COMMAND = "record"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--board", type=int, default=0, choices=range(MAX_DEV_BOARDS),
                        metavar="N", help="board number 0..3 (default 0)")
    parser.add_argument("-o", "--output", type=Path, required=True, metavar="SESSION",
                        help="the session directory to create (it may exist, empty); a "
                             "recording never overwrites a session")
    parser.add_argument("--seconds", type=float, default=None, metavar="S",
                        help="end the recording after S seconds (default: on Ctrl-C or "
                             "SIGTERM, or when the card stops)")
    parser.add_argument("--dpm-dir", "--image-dir", dest="dpm_dir", default=None,
                        metavar="DIR",
                        help=f"the card's image directory (default $CIF_DPM_DIR or "
                             f"{DEFAULT_DPM_DIR})")


class _Stop(Exception):
    """SIGINT or SIGTERM: end the recording."""


def _stop(signum: int, frame: FrameType | None) -> None:
    del signum, frame
    raise _Stop


def run(args: argparse.Namespace) -> int:
    if args.seconds is not None and args.seconds <= 0:
        print(f"cifemu {COMMAND}: --seconds must be more than 0", file=sys.stderr)
        return 1
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, _stop)
    image = image_path(dpm_dir(args.dpm_dir), args.board)
    try:
        attachment = attach(image, args.board, args.output)
    except (RecordingError, _Stop) as exc:
        if isinstance(exc, _Stop):
            return 1
        print(f"cifemu {COMMAND}: {exc}", file=sys.stderr)
        return 1
    ends = f"after {args.seconds:g} s" if args.seconds is not None else "on Ctrl-C"
    print(f"recording board {args.board} into {args.output}; it ends {ends}", flush=True)
    deadline = None if args.seconds is None else time.monotonic() + args.seconds
    try:
        try:
            while deadline is None or time.monotonic() < deadline:
                left = None if deadline is None else max(0.0, deadline - time.monotonic())
                if select.select([attachment], [], [], left)[0]:
                    break  # the card ended the recording: it stops
        except _Stop:
            pass
        # a second Ctrl-C while the writer finishes must not leave the session half told
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        print(f"writing the session into {args.output}", flush=True)
        summary = attachment.detach(timeout=None)  # the card's socket closes if it dies
    except RecordingError as exc:
        print(f"cifemu {COMMAND}: {exc}", file=sys.stderr)
        return 1
    print(_summary_line(args.board, args.output, summary))
    return 0 if summary.complete else 1


def _summary_line(board: int, session: Path, summary: Summary) -> str:
    line = (f"board {board}: {summary.events} events and {summary.frames} frames recorded "
            f"into {session}")
    if summary.card_stopped:
        line += "; the card stopped"
    if not summary.complete:
        line += "; the card's session writer failed, the session ends early (see its log)"
    return line
