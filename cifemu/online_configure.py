"""``cifemu firmware --configure``: the card configures itself on line once it is up [ours].

A host inside the firmware process does what `cifemu configure` does from
outside: it waits for READY, then talks to the card through the driver API and
the image like any other host (COM_Start_Seq / COM_Download / COM_End_Seq), so
the card is configured by the same path a user's program takes. A refusal
stops the card: a command line that asked for a running network must not
leave an unconfigured card behind looking healthy.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path

from cifemu.commands.configure import configure, msg_f_text
from dbm_tools.builder import BuildError, build_dbm
from dbm_tools.network import NetworkError, load_network
from dpm import flags as fl
from dpm.layout import HOST_FLAGS
from firmware.device import Device
from host_api.board import Board, CifError
from host_api.online import ConfigurationError

log = logging.getLogger(__name__)

NETWORK_WAIT_S = 10.0


ANSWER_TIMEOUT_MS = 5000
"""[ours] How long the card's own host waits for each answer. The card answers within
milliseconds; a machine loaded by other work (a test suite beside two busy processes) has
delayed one by over a second, and then the card stopped, its configuration half done."""


class OnlineConfiguration(threading.Thread):
    """Configure ``device`` from ``path`` once it is READY; ``failed`` tells how it went."""

    def __init__(self, device: Device, path: Path) -> None:
        super().__init__(name="online-configure", daemon=True)
        self.device = device
        self.path = path
        self.failed = False

    def _wait_ready(self) -> bool:
        """True once READY shows; False when the card stops first."""
        while not self.device.sleep(0.02):
            if self.device.mm[HOST_FLAGS] & fl.READY:
                return True
        return False

    def run(self) -> None:
        try:
            network = load_network(self.path)
            build_dbm(network)  # a description the card would refuse never reaches it
        except (NetworkError, BuildError, OSError) as exc:
            self._fail(f"--configure {self.path}: {exc}")
            return
        if not self._wait_ready():
            return
        try:
            with Board(self.device.board, self.device.directory,
                       timeout=ANSWER_TIMEOUT_MS) as board:
                outcome = configure(board, network, NETWORK_WAIT_S,
                                    lambda step: log.info("configuring: %s", step))
        except CifError as exc:
            self._fail(f"--configure: {exc}")
            return
        except ConfigurationError as exc:
            self._fail(f"--configure: {exc} ({msg_f_text(exc.f)})")
            return
        if outcome["missing"]:
            log.warning("configured, but node(s) %s not in data exchange (Err_Event %d: %s)",
                        outcome["missing"], outcome["err_event"], outcome["err_text"])
        else:
            log.info("configured on line from %s: %d node(s) in data exchange", self.path,
                     len(outcome["nodes"]))

    def _fail(self, text: str) -> None:
        log.error("%s; the card stops", text)
        self.failed = True
        self.device.stop()
