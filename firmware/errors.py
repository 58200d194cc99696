"""The root of the exceptions the firmware package raises of its own.

A program that runs a card (``Device``, the CAN controller, the simulated nodes) needs
one ``except FirmwareError`` for the firmware's own refusals. What it passes through
keeps its own family: python-can's ``CanError`` from a bus (the ``shm`` interface is a
python-can interface and raises what python-can's contract names), ``OSError`` from the
image and flash files, ``BoardBusyError`` (``dpm.image``) when another firmware serves
the board, ``DbmError`` and ``NetworkError`` (``dbm_tools``) from a database or a
network description.
"""

from __future__ import annotations


class FirmwareError(Exception):
    """Something the emulated card refuses to do; the message says why."""


class BusSetupError(FirmwareError, ValueError):
    """A bus that cannot be used as asked (e.g. cyclic sending outside the interpreter on an
    interface without it). A ValueError as well: it is an argument the caller chose."""
