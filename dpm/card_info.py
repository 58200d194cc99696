"""The facts a running firmware publishes beside its image, as the tools read them [ours].

The image has no room for the facts a person operating the card asks first: which
database the last start loaded from flash, which bus the controller is on, where its
frame tap is. At every start the firmware writes them to ``<dir>/board<N>.card.json``
(``firmware.card_info`` writes it); ``cifemu status``, ``top`` and ``monitor`` read it
here. Like the doorbell and the frame tap it is a contract between the firmware and the
host tools, so it lives in ``dpm``. The keys:

- ``pid``, ``board``, ``image``, ``flash``: the firmware's process and files;
- ``database``: None (no database in flash) or ``name``, ``date``, ``nodes``,
  ``usable``, ``faults``, ``stored_at`` of the one the start found;
- ``bus``: ``interface``, ``channel``, ``bitrate``, ``sets_bitrate``, ``baud_rate``,
  ``fatal`` of the controller;
- ``tap``: the frame tap's socket path (``dpm.tap``), None when the card offers none.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def card_info_path(directory: Path, board: int) -> Path:
    return directory / f"board{board}.card.json"


def read_card_info(directory: Path, board: int) -> dict[str, Any] | None:
    """The facts of the last start, or None when no firmware published any."""
    try:
        data = json.loads(card_info_path(directory, board).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None
