"""The emulated card's firmware: the device loop, its tasks, the CANopen master, the flash.

- ``Device`` (``firmware.device``): one card serving its image, with the RCS, PLC and
  CAN tasks (``rcs``, ``plc``, ``can_task``);
- ``firmware.can``: the CANopen master (controller, node handlers, SDO, SYNC);
- ``firmware.shm``: the ``shm`` python-can interface;
- ``FlashStore`` (``firmware.flash``): the card's flash directory;
- ``firmware.sim``: simulated CANopen nodes;
- ``FirmwareError`` (``firmware.errors``): the root of what the firmware raises.

The names load on first use, as does ``__version__`` (the package metadata): python-can's
interface registry imports ``firmware.shm.bus``, and the SYNC timer process (``python -m
firmware.shm.cyclic``, which must start within a fraction of a second) ``firmware.shm.station``,
and neither must pay for the device and its tasks.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from firmware.device import Device
    from firmware.errors import BusSetupError, FirmwareError
    from firmware.flash import FlashStore

    __version__: str

_HOMES = {
    "BusSetupError": "firmware.errors",
    "Device": "firmware.device",
    "FirmwareError": "firmware.errors",
    "FlashStore": "firmware.flash",
}

__all__ = ["BusSetupError", "Device", "FirmwareError", "FlashStore", "__version__"]


def __getattr__(name: str) -> Any:
    """``firmware.Device`` and the others, imported from their module when first asked for."""
    if name == "__version__":
        from importlib.metadata import version

        return version("cifemu")
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'firmware' has no attribute {name!r}")
    return getattr(import_module(home), name)
