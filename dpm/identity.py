"""What the emulated card says about itself in the image's identification areas.

VERSIONINFO, FIRMWAREINFO, TASKINFO, RCSINFO and DEVINFO are the card's header (seed 3,
docs/dpm.md 1): a host reads them to tell which card and firmware it talks to, so their
values are the card's numbers and live here with the layout; ``firmware.info`` writes them.
"""

from __future__ import annotations

FIRMWARE_NAME = b"CANopen Master"
"""[ours] abFirmwareName: the real card's firmware name is not in the seed."""
FIRMWARE_VERSION = b"V1.070 cifemu"
DEVICE_NUMBER = 1250100
"""[ours] ulDeviceNo of the emulated card."""
RCS_VERSION = 0x0100
DEV_TYPE = 0x32
DEV_MODEL = 0x05
TASKS = {1: (b"PLC", 0x0100), 2: (b"CAN", 0x0100)}
"""TASKINFO entries by index: entry 2 (task 2) "PLC", entry 3 (task 3) "CAN"."""
