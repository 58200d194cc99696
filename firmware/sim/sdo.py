"""SDO server of a simulated node: canopen's server plus what a real device does more.

canopen's ``SdoServer`` does expedited and segmented transfers against the
``LocalNode``'s object dictionary. Added here: no answer at all outside
PRE-OPERATIONAL and OPERATIONAL (CiA 301 table 41), injected aborts on chosen
objects, broken responses (fault ``sdo_response``: an undefined command
specifier, or a frame shorter than 8 bytes, as a non-conforming device sends
them), "sub-index does not exist" for array entries the object dictionary
does not define (canopen invents them from the first entry), abort 05040001h
for a segment outside a segmented transfer and for block download (canopen
trips over both and logs them as its own errors), and the node's after-write
work (PDO reconfiguration, the I/O echo) once a download is stored.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from canopen.objectdictionary import ODArray, ODVariable
from canopen.sdo.constants import (
    EXPEDITED,
    NO_MORE_DATA,
    RESPONSE_UPLOAD,
    SDO_STRUCT,
    SIZE_SPECIFIED,
)
from canopen.sdo.exceptions import SdoAbortedError
from canopen.sdo.server import SdoServer

from dpm.cia301 import (
    ABORT_GENERAL,
    ABORT_NO_DATA,
    ABORT_NO_SUBINDEX,
    ABORT_UNKNOWN_COMMAND,
    SDO_INITIATE,
    SDO_REQUEST_BASE,
    SDO_RESPONSE_BASE,
)
from firmware.frames import SDO_FRAME_LENGTH

if TYPE_CHECKING:
    from firmware.sim.node import SimulatedNode

UNKNOWN_COMMAND = 0xE0
"""Command byte of server command specifier 7, which CiA 301 leaves undefined."""
SHORT_LENGTH = 4


class SimSdoServer(SdoServer):
    def __init__(self, node: SimulatedNode) -> None:
        node_id = node.node_id
        super().__init__(SDO_REQUEST_BASE + node_id, SDO_RESPONSE_BASE + node_id, node)  # type: ignore[no-untyped-call]
        self._sim = node
        # canopen's abort() packs these; they stay None until a valid request otherwise.
        self._index = 0
        self._subindex = 0
        self._segmented: str | None = None
        """"upload" or "download" while a segmented transfer runs."""

    def on_request(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._sim.lock:
            if not self._sim.serves_sdo or len(data) != SDO_FRAME_LENGTH:
                return
            super().on_request(can_id, data, timestamp)  # type: ignore[no-untyped-call]
            if self._sim.written:  # an upload stored nothing: no call for it
                self._sim.after_writes()

    def init_upload(self, request: bytearray) -> None:
        """The initiate upload response: the value in it (expedited, up to four bytes) or
        its size (segmented), from the node's ``get_data`` as canopen's server answers it.

        Made here rather than by canopen's ``init_upload``, which logs each upload at INFO
        (two Python calls, as each of its responses through ``send_response``'s ``super``):
        the card's host SDO runs the node's server in the card's device loop (issue 22).
        canopen's ``on_request`` still calls it and turns what it raises into the abort."""
        index, subindex = self._check(request)
        self._buffer = None
        value = self._node.get_data(index, subindex, check_readable=True)
        size = len(value)
        if size == 0:
            raise SdoAbortedError(ABORT_NO_DATA)  # nothing to upload, as canopen answers
        if size <= 4:
            command = RESPONSE_UPLOAD | EXPEDITED | SIZE_SPECIFIED | (4 - size) << 2
            response = SDO_INITIATE.pack(command, index, subindex) + bytes(value).ljust(4, b"\0")
            self._segmented = None
        else:
            response = (SDO_INITIATE.pack(RESPONSE_UPLOAD | SIZE_SPECIFIED, index, subindex)
                        + size.to_bytes(4, "little"))
            self._buffer = bytearray(value)
            self._toggle = 0
            self._segmented = "upload"
        self.send_response(response)

    def init_download(self, request: bytearray) -> None:
        self._check(request)
        self._buffer = None
        super().init_download(request)  # type: ignore[no-untyped-call]
        self._segmented = "download" if self._buffer is not None else None

    def segmented_upload(self, command: int) -> None:
        if self._segmented != "upload":
            raise SdoAbortedError(ABORT_UNKNOWN_COMMAND)
        super().segmented_upload(command)  # type: ignore[no-untyped-call]
        if not self._buffer:
            self._segmented = None

    def segmented_download(self, command: int, request: bytearray) -> None:
        if self._segmented != "download":
            raise SdoAbortedError(ABORT_UNKNOWN_COMMAND)
        super().segmented_download(command, request)  # type: ignore[no-untyped-call]
        if command & NO_MORE_DATA:
            self._segmented = None

    def block_download(self, data: bytearray) -> None:
        _, self._index, self._subindex = SDO_STRUCT.unpack_from(data)
        raise SdoAbortedError(ABORT_UNKNOWN_COMMAND)  # not supported

    def request_aborted(self, data: bytearray) -> None:
        self._segmented = None
        super().request_aborted(data)  # type: ignore[no-untyped-call]

    def abort(self, abort_code: int = ABORT_GENERAL) -> None:
        self._segmented = None
        super().abort(abort_code)  # type: ignore[no-untyped-call]

    def send_response(self, response: bytes | bytearray) -> None:
        """Every response, aborts included, leaves here: the one place to break them."""
        fault = self._sim.description.sim.sdo_response
        if fault == "unknown":
            response = bytes([UNKNOWN_COMMAND]) + bytes(response[1:SDO_FRAME_LENGTH])
        elif fault == "short":
            response = bytes(response[:SHORT_LENGTH])
        # canopen's ``send_response`` is this one line: called here, not through ``super``
        # (its responses are bytearrays, which its ``send_message`` takes as it takes bytes)
        self.network.send_message(self.tx_cobid, response)  # type: ignore[arg-type]

    def _check(self, request: bytearray) -> tuple[int, int]:
        """The request's index and subindex (kept for an abort), after the node's own
        refusals: an injected abort, a subindex an array does not define."""
        _, index, subindex = SDO_STRUCT.unpack_from(request)
        self._index, self._subindex = index, subindex
        code = self._sim.description.sim.sdo_abort.get((index, subindex))
        if code is not None:
            raise SdoAbortedError(code)
        # ``indices``, not ``get``: the dictionary is a Mapping, whose ``get`` and the ABC's
        # ``isinstance`` cost Python calls; an ODVariable (not an ABC) is ruled out first.
        obj = self._sim.object_dictionary.indices.get(index)
        if (obj is not None and not isinstance(obj, ODVariable) and isinstance(obj, ODArray)
                and subindex not in obj.subindices):
            raise SdoAbortedError(ABORT_NO_SUBINDEX)
        return index, subindex
