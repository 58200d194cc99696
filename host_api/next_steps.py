"""What a refusal tells its user to do next: the command to run, ready to paste [ours].

A command that gives up names the way through, with the options that reach the same
card (``--board``, ``--dpm-dir`` where they differ from the defaults), so the line a
user copies works in a second terminal as it stands.
"""

from __future__ import annotations

from pathlib import Path

from dpm.errors import CanF


def card_options(board: int, directory: str | Path | None) -> str:
    """`` --board N --dpm-dir DIR`` as a command line needs them to reach this card
    (nothing for board 0 in the default directory)."""
    words = f" --board {board}" if board else ""
    return words + (f" --dpm-dir {directory}" if directory is not None else "")


def configure_refusal(f: int, network: str, board: int, directory: str | Path | None) -> str:
    """The next step after the CAN task refused an on-line configuration with msg.f ``f``.

    Seed 5.2.2 and chapter 7: a card that started from a database in its flash takes no
    on-line download; the database has to go first (a card without one starts empty and
    waits for the on-line data sets), or the new network goes into the flash instead.
    """
    card = card_options(board, directory)
    if f == CanF.FLASH_DATABASE_RUNS:
        return ("the card runs the database stored in its flash and takes no on-line "
                f"configuration beside it: `cifemu dbm delete{card}` and then "
                f"`cifemu configure {network}{card}` again; or store this network instead: "
                f"`cifemu dbm build {network} -o network.dbm` and "
                f"`cifemu dbm download network.dbm --reset{card}`")
    if f == CanF.SEQUENCE:
        return (f"another host may be configuring the card: `cifemu reset{card}` starts it "
                f"afresh, then `cifemu configure {network}{card}`")
    return (f"`cifemu dbm build {network} -o network.dbm` and `cifemu dbm check network.dbm` "
            "show the data set the card refuses")
