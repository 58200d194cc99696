"""README.md stays true, and every --help text is plain text a person reads in a terminal.

Each fenced ``python`` and ``sh`` block of the README, and of the docs pages that carry the
README's longer examples (``RUN_PAGES``), runs as written, in a directory of its
own, against a running card that simulates the README's own example network (its first
``toml`` block, saved there as ``network.toml``; ``tests/`` is the clone's, as a block pasted
at the clone's root sees it) and is configured with it on line. A block
that cannot run says why in an HTML comment on the line before it,
``<!-- not run by tests/test_readme.py: REASON -->``, and its test skips with that reason.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from cifemu.cli import build_parser
from dbm_tools.network import load_network
from dpm.layout import TASK2_STATE, TASK_STATE_SIZE
from dpm.task2 import ComDiagnostics
from host_api.board import Board
from host_api.online import configure_online
from tests import commands
from tests.conftest import ROOT, Card, start_card, wait_until
from tests.readme_blocks import BLOCK_TIMEOUT, BLOCKS, NETWORK, README, RUNNABLE, Block


def test_the_readme_is_a_ten_minute_read() -> None:
    """What the project is, a quick start, the commands, the status, links: the rest is in
    docs/ (issue 21: 300 lines at most)."""
    assert len(README.read_text(encoding="utf-8").splitlines()) <= 300


def test_the_readme_has_runnable_blocks_and_marks_only_with_a_reason() -> None:
    runnable = [b for b in BLOCKS if b.language in RUNNABLE]
    assert [b for b in runnable if b.no_run is None], "no README block would run"
    assert all(b.no_run.strip() for b in runnable if b.no_run is not None)
    marked = [b.line for b in BLOCKS if b.no_run is not None and b.language not in RUNNABLE]
    assert not marked, f"blocks at lines {marked} are marked but would not run anyway"


@pytest.fixture
def configured_card(tmp_path: Path) -> Iterator[Card]:
    """A card simulating the README's network, configured on line, its nodes in data exchange."""
    network = tmp_path / "network.toml"
    network.write_text(NETWORK)
    card = start_card(tmp_path, 0, "--simulate", str(network), "--flash", str(tmp_path / "flash"))
    try:
        with Board(0, tmp_path, timeout=5000) as board:
            configure_online(board, load_network(network))
        nodes = sorted(node.id for node in load_network(network).nodes)
        mm = card.map()
        try:
            wait_until(lambda: ComDiagnostics.decode(
                bytes(mm[TASK2_STATE : TASK2_STATE + TASK_STATE_SIZE])).operating() == nodes,
                10, f"nodes {nodes} in data exchange")
        finally:
            mm.close()
        yield card
    finally:
        card.stop()


def blocks_to_run() -> list[Block]:
    return [b for b in BLOCKS if b.language in RUNNABLE and b.no_run is None]


@pytest.mark.parametrize("block", blocks_to_run(), ids=lambda b: f"{b.page}:{b.line}")
def test_readme_block_runs_as_written(block: Block, configured_card: Card, tmp_path: Path) -> None:
    work = tmp_path / "work"
    work.mkdir()
    (work / "network.toml").write_text(NETWORK)
    (work / "tests").symlink_to(ROOT / "tests")  # the clone's C examples, as from its root
    env = dict(os.environ, CIF_DPM_DIR=str(configured_card.directory),
               PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    command = ([sys.executable, "-c", block.code] if block.language == "python"
               else ["bash", "-e", "-u", "-o", "pipefail", "-c", block.code])
    result = commands.run(command, cwd=work, env=env, capture_output=True, text=True,
                          timeout=BLOCK_TIMEOUT)
    assert result.returncode == 0, (
        f"{block.page} line {block.line} ({block.language}) failed with exit {result.returncode}\n"
        f"--- stdout\n{result.stdout}--- stderr\n{result.stderr}")


@pytest.mark.parametrize("block", [b for b in BLOCKS if b.no_run is not None],
                         ids=lambda b: f"{b.page}:{b.line}")
def test_readme_block_not_run(block: Block) -> None:
    """Reports each block the README marks as not runnable, with the README's reason."""
    pytest.skip(f"{block.page} line {block.line} ({block.language}) not run: {block.no_run}")


# --- --help ---------------------------------------------------------------------------------

MARKUP = re.compile(r"``|:[a-z]+:`|`_\b|^\.\. ", re.M)
"""reST literal quotes, roles, link ends and directives."""


def subcommands(parser: argparse.ArgumentParser) -> Iterator[tuple[str, argparse.ArgumentParser]]:
    for action in parser._actions:  # argparse offers no public walk of its subcommands
        if isinstance(action, argparse._SubParsersAction):
            yield from action.choices.items()


def help_texts(parser: argparse.ArgumentParser, name: str) -> Iterator[tuple[str, str]]:
    yield name, parser.format_help()
    for sub_name, sub in subcommands(parser):
        yield from help_texts(sub, f"{name} {sub_name}")


HELP_TEXTS = dict(help_texts(build_parser(), "cifemu"))


@pytest.mark.parametrize("name", list(HELP_TEXTS))
def test_every_cifemu_help_is_plain_text(name: str) -> None:
    found = MARKUP.search(HELP_TEXTS[name])
    assert found is None, f"{name} --help has {found.group()!r}: {HELP_TEXTS[name]}"


HELP_MODULES = ("bench", "bench.can", "bench.cia309", "bench.lss", "bench.mailbox",
                "bench.exchange_io", "bench.dbm", "bench.scaling")

MODULE_HELPS = """
import contextlib, io, json, runpy, sys
helps = {}
for module in sys.argv[1:]:
    sys.argv = [module, "--help"]
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        try:
            runpy.run_module(module, run_name="__main__", alter_sys=True)
            code = 0
        except SystemExit as end:
            code = end.code if isinstance(end.code, int) else 0 if end.code is None else 1
    helps[module] = {"code": code, "stdout": out.getvalue()}
json.dump(helps, sys.stdout)
"""
"""``python -m MODULE --help`` of every module, as ``-m`` runs a module (runpy, as
``__main__``), one after another in one interpreter: one start-up and one import of the
benchmarks' shared libraries instead of one per module."""


@pytest.fixture(scope="module")
def module_helps() -> dict[str, dict[str, Any]]:
    result = commands.run([sys.executable, "-c", MODULE_HELPS, *HELP_MODULES], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    helps: dict[str, dict[str, Any]] = json.loads(result.stdout)
    return helps


@pytest.mark.parametrize("module", HELP_MODULES)
def test_every_module_help_is_plain_text(module: str,
                                         module_helps: dict[str, dict[str, Any]]) -> None:
    shown = module_helps[module]
    assert shown["code"] == 0 and shown["stdout"], f"python -m {module} --help: {shown}"
    assert not MARKUP.search(shown["stdout"]), f"python -m {module} --help: {shown['stdout']}"


def test_status_help_explains_the_card_to_a_canopen_engineer() -> None:
    text = HELP_TEXTS["cifemu status"]
    for word in ("HostFlags", "DevFlags", "CAPITALS", "lower case", "READY", "RUN", "COM",
                 "NOTREADY", "HOSTCOM/HOSTACK", "CAN_state", "OFFLINE", "OPERATE", "Nd_cfg",
                 "Nd_state", "Nd_diag", "Err_Event", "msg.f", "17 node does not answer",
                 "200 card not configured"):
        assert word in text, word
    assert "\n  Nd_state   nodes in data exchange" in text  # argparse kept the layout
