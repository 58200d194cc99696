"""The card commands of ``cifemu dbm``: a running card's flash database.

``dbm_tools.cli`` holds the file commands (show, check, build, diff), which need no
card; this module adds the commands that go through the driver (``CARD_HELP``), so that
dbm_tools stays a codec layer that never imports host_api. ``cifemu dbm`` is this
module's parser: both kinds of command under one name.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn, TransferSpeedColumn

from cifemu.cli_options import add_card_options
from cifemu.cli_output import fail, print_json, quiet_broken_pipe
from dbm_tools import cli as file_commands
from dbm_tools.cli import PROG, UsageError, load_any, plain
from dbm_tools.container import read_data_area, write_dbm
from dbm_tools.errors import DbmError
from dbm_tools.validate import check_dbm
from dpm.errors import drv_name, drv_text
from dpm.flags import COM, READY, RUN
from host_api.download import (
    CONFIGURATION_DOWNLOAD,
    DevDownload,
    delete_database,
    flash_directory,
    upload_database,
)
from host_api.driver import (
    COLDSTART,
    DRIVERINFO,
    GET_DRIVER_INFO,
    DevCloseDriver,
    DevExitBoard,
    DevGetInfo,
    DevInitBoard,
    DevOpenDriver,
    DevReset,
)

SETTLE_SECONDS = 1.0
"""How long ``download --reset`` waits for RUN after READY before it reports the flags."""
RESET_TIMEOUT_MS = 10_000

CARD_COMMANDS = ("download", "upload", "delete", "dir")
CARD_HELP = """
Card commands (a running cifemu firmware; --board N, --dpm-dir DIR):

  download FILE [--reset]     DevDownload into the card's flash (driver codes
                              and 1000 + msg.f on failure, e.g. 1020: not a
                              CANopen database)
  upload -o FILE              the card's stored database, as a DBM file
  delete                      erase the stored database (seed 5.2.2)
  dir                         the card's flash directory

A stored database takes effect at the card's next start.
"""
DESCRIPTION = f"{file_commands.__doc__}{CARD_HELP}"
"""``cifemu dbm --help``: the file commands, then the card commands."""


def describe(rc: int) -> str:
    """A driver code as the user reads it: name, number, meaning."""
    return f"{drv_name(rc)} ({rc}): {drv_text(rc)}"


class _Card:
    """DevOpenDriver + DevInitBoard for one command; raises UsageError when there is no card."""

    def __init__(self, board: int, directory: str | None) -> None:
        self.board = board
        rc = DevOpenDriver(directory)
        if rc != 0:
            raise UsageError(f"cannot open the image directory: {describe(rc)}")
        rc = DevInitBoard(board)
        if rc != 0:
            DevCloseDriver()
            raise UsageError(f"board {board}: {describe(rc)} (is `cifemu firmware "
                             f"--board {board}` running?)")

    def host_flags(self) -> int:
        rc, info = DevGetInfo(self.board, GET_DRIVER_INFO, DRIVERINFO.size)
        return int(DRIVERINFO.unpack(info)[11]) if rc == 0 else 0  # bHostFlags

    def cold_start(self) -> int:
        """DevReset(COLDSTART), then HostFlags once RUN shows (a configured card) or soon."""
        rc = DevReset(self.board, COLDSTART, RESET_TIMEOUT_MS)
        if rc != 0:
            raise UsageError(f"cold start failed: {describe(rc)}")
        deadline = time.monotonic() + SETTLE_SECONDS  # RUN and COM follow READY
        while not self.host_flags() & RUN and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.01)
        return self.host_flags()

    def close(self) -> None:
        DevExitBoard(self.board)
        DevCloseDriver()


def _progress(console: Console, what: str) -> Progress:
    return Progress(TextColumn(what), BarColumn(), DownloadColumn(), TransferSpeedColumn(),
                    console=console, transient=True)


def download(path: Path, board: int, directory: str | None, reset: bool,
             console: Console) -> int:
    """DevDownload ``path`` into the card's flash; raises UsageError with the driver's code."""
    try:
        errors = [f for f in check_dbm(load_any(path)) if f.severity == "error"]
    except UsageError:
        errors = []  # DevDownload judges what it cannot send
    if errors:
        console.print(f"[yellow]warning[/]: {path} fails {len(errors)} data check(s) "
                      f"(`{PROG} check`); the card will report Err_Event 212 at its next start")
    card = _Card(board, directory)
    try:
        with _progress(console, f"download {path.name}") as bar:
            task = bar.add_task("download", total=None)
            rc = DevDownload(board, CONFIGURATION_DOWNLOAD, path,
                             lambda done, total: bar.update(task, completed=done, total=total))
        if rc != 0:
            raise UsageError(f"download refused: {describe(rc)}")
        console.print(f"{path} stored in board {board}'s flash; it takes effect at the next start")
        if reset:
            flags = card.cold_start()
            state = [name for name, bit in (("READY", READY), ("RUN", RUN), ("COM", COM))
                     if flags & bit]
            console.print(f"cold start done: {' '.join(state)}")
    finally:
        card.close()
    return 0


def upload(output: Path, board: int, directory: str | None, console: Console) -> int:
    """The stored database into ``output``; raises UsageError when the card has none."""
    card = _Card(board, directory)
    try:
        with _progress(console, "upload") as bar:
            task = bar.add_task("upload", total=None)
            rc, area = upload_database(
                board, lambda done, total: bar.update(task, completed=done, total=total))
    finally:
        card.close()
    if rc != 0:
        raise UsageError(f"upload failed: {describe(rc)}")
    try:
        content = write_dbm(read_data_area(area))
    except DbmError as exc:
        console.print(f"[yellow]warning[/]: the stored database is not readable ({exc}); "
                      "writing the bare data area")
        content = area
    try:
        output.write_bytes(content)
    except OSError as exc:
        raise UsageError(f"cannot write {output}: {exc.strerror}") from None
    console.print(f"{output}: the database of board {board} ({len(area)} bytes of data area)")
    return 0


def delete(board: int, directory: str | None, console: Console) -> int:
    """Erase the stored database; raises UsageError with the driver's code."""
    card = _Card(board, directory)
    try:
        rc = delete_database(board)
    finally:
        card.close()
    if rc != 0:
        raise UsageError(f"delete failed: {describe(rc)}")
    console.print(f"board {board}: database deleted; from the next start the card waits "
                  "for an on-line configuration")
    return 0


def directory_listing(board: int, directory: str | None, as_json: bool,
                      console: Console) -> int:
    """The flash directory; raises UsageError with the driver's code."""
    card = _Card(board, directory)
    try:
        rc, entries = flash_directory(board)
    finally:
        card.close()
    if rc != 0:
        raise UsageError(f"flash directory failed: {describe(rc)}")
    if as_json:
        print_json([plain(e) for e in entries])
        return 0
    if not entries:
        console.print(f"board {board}: no database stored")
    for e in entries:
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(e.stored))
        console.print(f"board {board}: segment {e.segment} {e.name!r}, {e.length} bytes, "
                      f"w0 {e.checksum:#06x}, stored {when}", highlight=False)
    return 0


# --- command line ----------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The file commands of ``dbm_tools.cli`` and the card commands, under one parser."""
    sub = file_commands.add_arguments(parser)

    p = sub.add_parser("download", help="put a DBM into a card's flash (DevDownload)",
                       description="Download a DBM into a running card's flash with "
                       "DevDownload. Failures show the driver's code: -100..-105 for file "
                       "problems, 1000+f for the card's refusal (1020 not a CANopen database, "
                       "1022 wrong message number, 1023 wrong size, 1024 wrong sequence, "
                       "1025 checksum). The database takes effect at the next start.")
    p.add_argument("file", type=Path, metavar="FILE", help="the DBM file (*.dbm)")
    add_card_options(p)
    p.add_argument("--reset", action="store_true", help="cold-start the card afterwards")
    p = sub.add_parser("upload", help="read a card's stored database into a DBM file",
                       description="Upload the database stored in a running card's flash.")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="FILE",
                   help="the DBM file to write")
    add_card_options(p)
    p = sub.add_parser("delete", help="erase a card's stored database",
                       description="Delete the database in a running card's flash (seed "
                       "5.2.2). From its next start the card comes up READY without RUN and "
                       "takes an on-line configuration.")
    add_card_options(p)
    p = sub.add_parser("dir", help="list a card's flash directory",
                       description="What a running card's flash holds: segment, segment "
                       "name, size, checksum and when it was stored.")
    add_card_options(p)
    p.add_argument("--json", action="store_true", help="print the entries as JSON")


def _run_card_command(args: argparse.Namespace, console: Console) -> int:
    command = args.dbm_command
    if command == "download":
        return download(args.file, args.board, args.dpm_dir, args.reset, console)
    if command == "upload":
        return upload(args.output, args.board, args.dpm_dir, console)
    if command == "delete":
        return delete(args.board, args.dpm_dir, console)
    return directory_listing(args.board, args.dpm_dir, args.json, console)


def run(args: argparse.Namespace) -> int:
    """One command of ``cifemu dbm``, reported by the commands' JSON convention
    (``cifemu.cli_output``): a user's mistake is one line on stderr, or with ``--json``
    an error object on stdout, and exit status 1; a reader that leaves early
    (``--json | head``) ends the command without a traceback."""
    console = Console()
    try:
        if args.dbm_command in CARD_COMMANDS:
            result = _run_card_command(args, console)
        else:
            result = file_commands.dispatch(args, console)
        sys.stdout.flush()  # inside the guard: a closed pipe shows at the flush
    except UsageError as exc:
        return fail(f"dbm {args.dbm_command}", str(exc), getattr(args, "json", False))
    except BrokenPipeError:
        return quiet_broken_pipe()
    return result

