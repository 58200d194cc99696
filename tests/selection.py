"""Which tests run in which target, by module: make test-fast, make test, make test-vcan.

A module is ``fast`` unless it is listed in ``PROCESS_MODULES``: a new test module of codecs
or parsers joins ``make test-fast`` by itself, and one that starts a process or opens a
socket fails there (``forbid_processes``) with a message that says to list it, so the
selection neither shrinks nor grows a firmware unnoticed. ``tests/test_suite_rules.py``
checks that every name listed here is a test module that exists.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent

PROCESS_MODULES = frozenset({
    "test_bench_can", "test_bench_frame_cost", "test_bench_lss", "test_bench_scaling",
    "test_can_bus", "test_native_mailbox",
    "test_can_late_frames", "test_can_task",
    "test_can_unsupervised", "test_chaos", "test_cia309_gateway", "test_cia309_limits",
    "test_cia309_server", "test_configure_cli", "test_dbm_by_hand", "test_dbm_cli",
    "test_download", "test_suite_guards", "test_firmware", "test_fuzz_mailbox",
    "test_faults",
    "test_health", "test_host_restart", "test_hostile_image", "test_json_convention",
    "test_legacy", "test_libcif_c", "test_libcif_dbm", "test_libcif_driver",
    "test_libcif_headers", "test_lss", "test_monitor", "test_online_download",
    "test_raw_dpm", "test_readme", "test_seed_fidelity", "test_can_master_services", "test_shm_bus",
    "test_sim", "test_soak", "test_top", "test_vcan_tools", "test_vcan_vm",
    "test_cia309_slots", "test_libcif_hosts", "test_local_users", "test_newcomer",
    "test_pytest_plugin", "test_bus_parameter_set", "test_node_handlers", "test_idle",
    "test_remote_bus", "test_bridges_vcan", "test_bus_options", "test_busy_board",
    "test_dbm_export", "test_demo_view", "test_layers", "test_off_terminal", "test_parser_fuzz",
    "test_reset", "test_send", "test_record_replay", "test_socketcand_link",
    "test_record_attach", "test_tap", "test_bench_canopennode", "test_lock_table",
    "test_mailbox_rings", "test_mailbox_spin", "test_mailbox_calls", "test_recorder_cost",
    "test_boot_work", "test_first_boot", "test_host_sdo_path", "test_load_clock", "test_host_bell",
    "test_host_transaction",
    "test_card_power_off",
})
"""Modules whose tests start a process (a firmware, ``cifemu sim``, a command, a compiler),
open a socket or a shared-memory bus, or wait for a card's timers: not ``fast``."""

VCAN_VM_MODULES = frozenset({"test_vcan_vm"})
"""Modules that start a virtual machine (tools/vcan-vm's qemu, 2 minutes): ``make test-vcan``."""

SERIAL_MODULES = frozenset({"test_bench_frame_cost", "test_soak"})
"""Modules that measure the machine's time or throughput (the scaling bench's frame rates,
the soak's invariants): alone on it, never beside another pytest-xdist worker."""

SERIAL_TESTS = frozenset({
    ("test_sim", "test_heartbeat_at_the_configured_period"),
    ("test_idle", "test_a_ringing_host_s_new_outputs_reach_the_bus_at_once"),
})
"""Single tests, as (module, function), that measure wall time in a module that does not:
``serial`` like ``SERIAL_MODULES``. A simulated node's heartbeat period (its sending thread
runs in the test process: at load 18 too few beats went out between stalls to measure one)
and the card's 10 ms from a ringing host's new output to its RPDO (a median of 12 ms at load
15-21) are what load changes, not waits (docs/testing.md, the loaded runs)."""

SERIAL_PASS_MODULES = SERIAL_MODULES | {module for module, _ in SERIAL_TESTS}
"""The modules make test's serial pass collects (``-m serial`` then picks the tests)."""

HELPER_MODULES = tuple(
    f"tests.{path.stem}" for path in sorted(TESTS.glob("*.py"))
    if not path.stem.startswith("test_") and path.stem not in ("__init__", "conftest",
                                                                "selection"))
"""The fixtures and helpers the test modules import (``tests/buses.py``, ...): never a test
module, which no other module imports."""


def marks_of_test(module: str, name: str) -> list[pytest.MarkDecorator]:
    """The markers of test function ``name`` of ``module``: its module's, and ``serial``
    when it is one of ``SERIAL_TESTS``."""
    marks = marks_of_module(module)
    if (module, name) in SERIAL_TESTS and module not in SERIAL_MODULES:
        marks.append(pytest.mark.serial)
    return marks


def marks_of_module(module: str) -> list[pytest.MarkDecorator]:
    """The markers every test of ``module`` (a file name without ``.py``) carries."""
    marks = []
    if module not in PROCESS_MODULES:
        marks.append(pytest.mark.fast)
    if module in VCAN_VM_MODULES:
        marks.append(pytest.mark.vcan_vm)
    if module in SERIAL_MODULES:
        marks.append(pytest.mark.serial)
    return marks


FORBIDDEN_EVENTS = frozenset({
    "subprocess.Popen", "os.fork", "os.forkpty", "os.posix_spawn", "os.system", "os.exec",
    "socket.bind", "mmap.__new__",
})
"""The audit events of a test that is not ``fast``: a child process, a socket that serves, a
mapped image (a card's or a shared-memory bus's). A connect stays allowed: with nothing started
there is nobody to answer it (the command-line fuzz tries ``cifemu 309 exec --port``)."""

NOT_FAST = ("make test-fast runs only tests that start no process, serve no socket and map "
            "no image: {event} here, so add this module to PROCESS_MODULES in "
            "tests/selection.py")


def _audit(event: str, args: tuple[object, ...]) -> None:
    del args
    if event in FORBIDDEN_EVENTS:
        raise RuntimeError(NOT_FAST.format(event=event))


def forbid_processes() -> None:
    """From now on, this process raises at every ``FORBIDDEN_EVENTS`` event. An audit hook
    cannot be removed: call it only in a process that runs nothing but fast tests."""
    sys.addaudithook(_audit)


def module_paths(modules: frozenset[str] | set[str]) -> list[str]:
    """The files of ``modules``, relative to the clone's root, as pytest takes them."""
    return [str(TESTS.relative_to(TESTS.parent) / f"{module}.py") for module in sorted(modules)]


if __name__ == "__main__":
    # ``python -m tests.selection serial``: the files of the serial modules and of the
    # serial tests, for make test's second pass, which then collects only them and not the
    # whole suite once more.
    if sys.argv[1:] != ["serial"]:
        raise SystemExit("usage: python -m tests.selection serial")
    print(" ".join(module_paths(SERIAL_PASS_MODULES)))
