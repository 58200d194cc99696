"""The process data as the bus sees it, decoupled from the DPM areas.

In the buffered modes the CAN task drives ``outputs`` and fills ``inputs``;
the PLC task copies between them and the image only at a handshake, under a
lock, so a host never sees half of one PDO and half of the next. In the
uncontrolled mode the image itself is the process data.
"""

from __future__ import annotations

import mmap
import threading

from dpm.layout import IO_AREA_SIZE, RCV_PD, SND_PD

UNCONTROLLED = 3
_SND_END, _RCV_END = SND_PD + IO_AREA_SIZE, RCV_PD + IO_AREA_SIZE


class ProcessImage:
    def __init__(self, image: mmap.mmap) -> None:
        self._mm = image
        self.lock = threading.RLock()  # re-entered by bit read-modify-write
        self.outputs = bytearray(IO_AREA_SIZE)
        self.inputs = bytearray(IO_AREA_SIZE)
        self.mode = 0
        self.driving = True
        """False while the host is not ready or its watchdog expired: outputs read as 0."""
        self._flips: dict[int, int] = {}
        """[ours] Input bits the fault "flip" inverts in RcvPd: byte offset -> mask."""
        self._flip_once = False
        self.exchanged_changes = True
        """[ours] Whether an exchange may have left SndPd as the card took it (``outputs``)
        or RcvPd as it wrote it different from what the exchange before left, since a
        recording last took both (``Recorder.settle`` clears it, and sets it when it
        starts): set by the exchange that found a difference and by each write of
        ``outputs`` beside the image's SndPd. The recorder compared 7 KiB of snapshots of its
        own instead, read once per exchange and out of the cache by then: about a third of
        what recording cost the exchange loop's card (docs/benchmarks.md, note 8)."""

    def clear(self) -> None:
        with self.lock:
            self.outputs[:] = bytes(IO_AREA_SIZE)
            self.inputs[:] = bytes(IO_AREA_SIZE)
            self.exchanged_changes = True

    def read_outputs(self, offset: int, size: int) -> bytes:
        """What the bus should carry for the host outputs at ``offset``."""
        with self.lock:
            if not self.driving:
                return bytes(size)
            if self.mode == UNCONTROLLED:
                return self._mm[SND_PD + offset : SND_PD + offset + size]
            return bytes(self.outputs[offset : offset + size])

    def snapshot_outputs(self) -> bytes:
        """All outputs at once: the CAN task compares them to find changed PDOs."""
        with self.lock:
            if self.mode == UNCONTROLLED:
                return self._mm[SND_PD : SND_PD + IO_AREA_SIZE]
            return bytes(self.outputs)

    def write_inputs(self, offset: int, data: bytes) -> None:
        """Store what the bus delivered; visible at once in the uncontrolled mode."""
        with self.lock:
            self.inputs[offset : offset + len(data)] = data
            if self.mode == UNCONTROLLED:
                self._mm[RCV_PD + offset : RCV_PD + offset + len(data)] = data
                for flipped, mask in self._flips.items():
                    if offset <= flipped < offset + len(data):
                        self._mm[RCV_PD + flipped] = self.inputs[flipped] ^ mask

    def read_inputs(self, offset: int, size: int) -> bytes:
        with self.lock:
            return bytes(self.inputs[offset : offset + size])

    def read_send_area(self, offset: int, size: int) -> bytes:
        return self._mm[SND_PD + offset : SND_PD + offset + size]

    def write_send_area(self, offset: int, data: bytes) -> None:
        """A consistent write into the host outputs (COM_Shared_Memory)."""
        with self.lock:
            self._mm[SND_PD + offset : SND_PD + offset + len(data)] = data
            self.outputs[offset : offset + len(data)] = data
            self.exchanged_changes = True

    def cycle(self) -> None:
        """One buffered exchange: take the host's outputs, hand it the inputs. Each area is
        compared before it is copied (the copy reads and writes the same bytes): one that did
        not change is not written, and ``exchanged_changes`` tells a recording."""
        with self.lock:
            mm = self._mm
            taken = mm[SND_PD:_SND_END]
            if taken != self.outputs:
                self.outputs[:] = taken
                self.exchanged_changes = True
            if self._flips or mm.find(self.inputs, RCV_PD, _RCV_END) != RCV_PD:
                mm[RCV_PD:_RCV_END] = self.inputs
                self.exchanged_changes = True
            if self._flips:
                for offset, mask in self._flips.items():
                    self._mm[RCV_PD + offset] = self.inputs[offset] ^ mask
                if self._flip_once:
                    self._flips = {}

    # --- the fault "flip" [ours] (firmware/faults.py) -----------------------------------

    @property
    def flipping(self) -> bool:
        """Whether a flipped input bit is still to come (or, for a duration, in force)."""
        return bool(self._flips)

    def flip_inputs(self, offset: int, mask: int, once: bool) -> None:
        """Invert the ``mask`` bits of input byte ``offset`` as the host receives it: at
        the next buffered exchange (``once``) or at every one until ``unflip_inputs``. In
        the uncontrolled mode the image is the process data: the byte is inverted at once
        and, for a duration, again whenever the bus writes it."""
        with self.lock:
            if self.mode == UNCONTROLLED:
                self._mm[RCV_PD + offset] = self.inputs[offset] ^ mask
                if once:
                    return
            self._flips = {offset: mask}
            self._flip_once = once

    def unflip_inputs(self) -> None:
        """End a flip: the next exchange (the uncontrolled mode: now) shows the true bits."""
        with self.lock:
            if self.mode == UNCONTROLLED:
                for offset in self._flips:
                    self._mm[RCV_PD + offset] = self.inputs[offset]
            self._flips = {}
