"""What a running firmware tells the tools beside its image [ours].

The image has no room for the facts a person operating the card asks first:
which database the last start loaded from flash, which bus the controller is
on, where its frame tap is. At every start the firmware writes them to
``<dir>/board<N>.card.json`` (mode 0660, replaced atomically through a new file
of an unpredictable name, so nothing planted in the directory is followed:
docs/security.md) and logs the database; ``cifemu status``, ``top`` and
``monitor`` read the file through ``dpm.card_info``, where its name and keys are.
"""

from __future__ import annotations

import json
import logging
import os
from typing import TYPE_CHECKING, Any

from dbm_tools.errors import DbmError
from dbm_tools.parameters import BAUD_RATES_KBIT
from dbm_tools.tables import NODES, PROJEKT, ProjektRecord
from dpm.card_info import card_info_path
from dpm.image import IMAGE_MODE

if TYPE_CHECKING:
    from firmware.flash import StoredDatabase
    from firmware.whole_card import WholeCard

log = logging.getLogger("firmware.rcs")


def describe_database(database: StoredDatabase | None, stored_at: float | None
                      ) -> dict[str, Any] | None:
    """Name, date, node count and verdict of the database a start found (None: no database)."""
    if database is None:
        return None
    name = date = ""
    nodes = 0
    if database.dbm is not None:
        projekt = database.dbm.table(PROJEKT)
        if projekt is not None and projekt.records:
            try:
                record = ProjektRecord.decode(projekt.records[0])
                name, date = record.szProjectName, record.szDate
            except DbmError:
                pass  # a faulty PROJEKT record: the faults below say what is wrong
        table = database.dbm.table(NODES)
        nodes = len(table.records) if table is not None else 0
    return {"name": name, "date": date, "nodes": nodes, "usable": database.usable,
            "faults": [text for _, _, text in database.faults], "stored_at": stored_at}


def log_database(info: dict[str, Any] | None) -> None:
    if info is None:
        log.info("no database in flash: waiting for an on-line configuration")
    elif info["usable"]:
        log.info("database from flash: %r of %s, %d node(s)", info["name"], info["date"] or "?",
                 info["nodes"])
    else:
        log.warning("database from flash: %r of %s, %d node(s), not used: %s", info["name"],
                    info["date"] or "?", info["nodes"], "; ".join(info["faults"]))


def publish(device: WholeCard) -> None:
    """Log the start's database and write the card's facts beside the image."""
    database = describe_database(device.database, device.flash.stored_at())
    log_database(database)
    master = device.can.master
    config = master.config
    bus = master.bus
    params = master.bus_params
    # One look at the link: a SocketCAN link's rate comes from ``ip`` (read once per
    # opening, ``firmware.can.bus.LinkRate``); the first look after the opening waits for it.
    bitrate = bus.bitrate if bus is not None else None
    info = {
        "pid": os.getpid(),
        "board": device.board,
        "image": str(device.path),
        "flash": str(device.flash.path),
        "database": database,
        "bus": {"interface": config.interface, "channel": config.channel,
                "bitrate": bitrate,
                "sets_bitrate": bus is not None and (bus.sets_bitrate or bitrate is not None),
                "baud_rate": BAUD_RATES_KBIT[params.Baud_rate] * 1000 if params else None,
                "fatal": device.can.fatal},
        "tap": os.fsdecode(config.tap) if config.tap else None,
    }
    name = card_info_path(device.directory, device.board).name
    device.files.replace(name, json.dumps(info, indent=2).encode(), IMAGE_MODE)

