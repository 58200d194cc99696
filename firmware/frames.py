"""What every station on the CAN bus relies on, the card's controller and the simulated nodes.

These are facts of the bus, not of the card: SocketCAN's error-frame classes and the
CANopen SDO frame length. They live apart from ``firmware.can`` (the card's master) and
``firmware.sim`` (the nodes it talks to), so that neither side imports the other to get
them; importing this module loads nothing else of the firmware.
"""

from __future__ import annotations

SDO_FRAME_LENGTH = 8
"""CiA 301: every SDO frame has 8 data bytes (seed 4.3, Err_Event 38)."""

# SocketCAN error classes (linux/can/error.h): python-can carries them in an error
# frame's identifier, and the controller-state details in its data byte 1.
CAN_ERR_TX_TIMEOUT = 0x001
CAN_ERR_CRTL = 0x004
CAN_ERR_PROT = 0x008
CAN_ERR_ACK = 0x020
CAN_ERR_BUSOFF = 0x040
CAN_ERR_CRTL_RX_OVERFLOW = 0x01
CAN_ERR_CRTL_RX_WARNING = 0x04
CAN_ERR_CRTL_TX_WARNING = 0x08
CAN_ERR_CRTL_RX_PASSIVE = 0x10
CAN_ERR_CRTL_TX_PASSIVE = 0x20
CAN_ERR_CRTL_LIMITS = (CAN_ERR_CRTL_RX_WARNING | CAN_ERR_CRTL_TX_WARNING
                       | CAN_ERR_CRTL_RX_PASSIVE | CAN_ERR_CRTL_TX_PASSIVE)
"""The controller's error counter crossed the warning or the error-passive limit."""
CAN_ERR_CRTL_ACTIVE = 0x40
"""The controller is back to error-active (its counters below the warning limit again)."""
CAN_ERR_RESTARTED = 0x100
"""The controller restarted after bus-off."""
