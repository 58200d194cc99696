"""cifemu replay: play a recorded session's host side against a card, and compare.

    cifemu replay SESSION [--board N] [--pace recorded]
    cifemu replay --diff A B

The first form does what the recorded host did (its messages, resets, NOTREADY changes
and outputs, in order) and compares what the host sees now with what it saw then: each
answer's header and data, the input image at each exchange, the card's levels and
Task2State at each step. The second compares two recorded sessions without a card.
Both print a diff of the two decoded transcripts, then each changed field, and exit
with status 1 when they differ (2 when a session cannot be read or a step not played).
docs/recording.md says what is compared and what is left out.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from dpm import session as s
from dpm.image import DEFAULT_DPM_DIR, MAX_DEV_BOARDS
from dpm.transcript import diff, transcript

EXIT_DIFFERENT = 1
EXIT_ERROR = 2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("sessions", nargs="+", type=Path, metavar="SESSION",
                        help="a session directory (cifemu firmware --record, cifemu record); "
                             "two with --diff")
    parser.add_argument("--diff", action="store_true",
                        help="compare the two recorded sessions A B, without a card")
    parser.add_argument("--board", type=int, default=0, choices=range(MAX_DEV_BOARDS),
                        metavar="N", help="board number 0..3 (default 0)")
    parser.add_argument("--dpm-dir", default=None,
                        help=f"the card's image directory (default $CIF_DPM_DIR or "
                             f"{DEFAULT_DPM_DIR})")
    parser.add_argument("--pace", choices=["fast", "recorded"], default="fast",
                        help="fast (default): each step as soon as the card has answered "
                             "and shows the recorded state; recorded: also keep the "
                             "recorded gaps between steps")
    parser.add_argument("--step-timeout", type=float, default=5.0, metavar="SECONDS",
                        help="how long a step waits for an answer or the recorded state "
                             "(default 5)")


def read_session(path: Path) -> list[s.Record]:
    """A session directory's records; SessionError or OSError when it is not one."""
    s.decode_meta((path / s.META).read_text(encoding="utf-8"))
    return s.decode_events((path / s.EVENTS).read_text(encoding="ascii"))


def run(args: argparse.Namespace) -> int:
    expected = 2 if args.diff else 1
    if len(args.sessions) != expected:
        print(f"cifemu replay: {'--diff takes' if args.diff else 'give'} {expected} "
              f"session{'s' if expected > 1 else ''}", file=sys.stderr)
        return EXIT_ERROR
    try:
        recorded = read_session(args.sessions[0])
        if args.diff:
            other = read_session(args.sessions[1])
            names = (str(args.sessions[0]), str(args.sessions[1]))
        else:
            from host_api.replay import Player, ReplayError

            player = Player(args.board, args.dpm_dir, args.step_timeout,
                            pace_recorded=args.pace == "recorded")
            try:
                other = player.play(recorded)
            except ReplayError as exc:
                print(f"cifemu replay: {exc}", file=sys.stderr)
                return EXIT_ERROR
            names = (f"{args.sessions[0]} (recorded)", f"board {args.board} (now)")
    except (s.SessionError, OSError) as exc:
        print(f"cifemu replay: {exc}", file=sys.stderr)
        return EXIT_ERROR
    lines = diff(transcript(recorded), transcript(other), *names)
    for line in lines:
        print(line)
    if not lines:
        print(f"cifemu replay: no difference ({len(transcript(recorded))} steps)")
    return EXIT_DIFFERENT if lines else 0
