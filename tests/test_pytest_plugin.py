"""The pytest plugin ``cifemu`` (cifemu/pytest_plugin.py), as a user's suite meets it.

The examples of docs/pytest-plugin.md (examples/pytest/) run in a pytest of their own, in a
fresh directory with none of this project's conftest or ini: the fixture comes from the
installed entry point alone, as in a user's project. A failing test generated beside them
must show the card's side in its report; a network the card cannot use must fail the
set-up in one line. The rest uses ``cif_card`` in this suite directly: the plugin is
loaded here as everywhere cifemu is installed.
"""

from __future__ import annotations

import os
import re
import shutil
import sys
import tomllib
from pathlib import Path

import pytest

from cifemu.pytest_plugin import CardError, CifCard, network_toml
from host_api.board import Board
from tests import commands
from tests.conftest import wait_until

pytest_plugins = ["pytester"]

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples" / "pytest"
EXAMPLE_TESTS = 4
"""test_host_program.py's three and test_c_program.py's one."""

FAILING = '''
import pytest
from host_program import write_and_confirm


@pytest.mark.cif_network("network.toml")
def test_the_echo_is_not_what_the_user_expected(cif_card):
    cif_card.wait_until_operating()
    assert write_and_confirm(0, 0, b"\\x11" * 8) == b"\\x22" * 8


@pytest.mark.cif_network({"node": [{"id": 300}]})
def test_a_network_the_card_cannot_use(cif_card):
    pass
'''


def user_project(pytester: pytest.Pytester) -> None:
    """The examples in a directory of their own, as a user's project holds them."""
    for path in EXAMPLES.iterdir():
        if path.is_file():
            shutil.copy(path, pytester.path / path.name)


def processes_mentioning(text: str) -> list[str]:
    """Command lines of running processes that contain ``text`` (a card's directory)."""
    found = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            words = cmdline.read_bytes().split(b"\0")
        except OSError:  # ended meanwhile
            continue
        line = " ".join(w.decode(errors="replace") for w in words)
        if text in line:
            found.append(line)
    return found


@pytest.mark.timeout(900)
def test_the_examples_pass_and_a_failing_test_shows_the_card(pytester: pytest.Pytester) -> None:
    user_project(pytester)
    pytester.makepyfile(test_user_fails=FAILING)
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider", "--strict-markers",
                                           timeout=840)
    result.assert_outcomes(passed=EXAMPLE_TESTS, failed=1, errors=1)
    result.stdout.fnmatch_lines([f"rootdir: {pytester.path}"])  # none of this project's
    out = result.stdout.str()
    # the failed test's report carries the card's log and its final state, once
    failure = out[out.index("_ test_the_echo_is_not_what_the_user_expected _"):]
    failure = failure[:failure.index("short test summary info")]
    assert "AssertionError" in failure
    assert "- cifemu board 0: firmware log -" in failure
    # logged before the network starts; its "in data exchange" line comes from the card's
    # own wait, which may still be polling when the user's test has already failed
    assert "configuring: node 2" in failure
    assert "- cifemu board 0: status -" in failure
    assert '"nd_state": [\n      1,\n      2\n    ]' in failure
    assert '"inputs": "1111111111111111' in failure  # what the host read: the echo
    assert "- cifemu board 0: transcript -" in failure  # what the host did, from the recording
    assert "exchange: SndPd[0] 1111111111111111" in failure
    assert out.count("- cifemu board") == 3, "sections for the failed test only"
    # a mistake in the marker: one line naming the key, no traceback into the plugin
    result.stdout.fnmatch_lines(["*cif_network: node 300: id = 300 is outside 1..127*"])
    assert "pytest_plugin.py" not in out
    # every card stopped: no process left with a card directory of this run
    assert processes_mentioning(str(pytester.path)) == []


@pytest.mark.timeout(300)
def test_without_the_plugin_there_is_no_cif_card(pytester: pytest.Pytester) -> None:
    """The entry point named ``cifemu`` is what provides the fixture: disabled by name,
    the examples find none."""
    user_project(pytester)
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider", "-p", "no:cifemu",
                                           "test_host_program.py", timeout=240)
    result.assert_outcomes(errors=3)
    result.stdout.fnmatch_lines(["*fixture 'cif_card' not found*"])


@pytest.mark.cif_network({"node": [{"id": 3}]}, board=2)
def test_the_card_is_the_tests_own_and_restarts(cif_card: CifCard, tmp_path: Path) -> None:
    assert cif_card.board == 2 and cif_card.log.is_relative_to(tmp_path)
    assert len(str(cif_card.image) + ".bell") < 108  # its sockets' paths fit sun_path
    assert os.environ["CIF_DPM_DIR"] == str(cif_card.directory)
    assert cif_card.wait_until_operating().operating() == [3]
    first = cif_card.pid
    cif_card.restart()
    assert cif_card.pid != first and not Path(f"/proc/{first}").exists()
    assert cif_card.wait_until_operating().operating() == [3]
    with Board(2) as board:  # found through $CIF_DPM_DIR
        assert board.diagnostics().operating() == [3]
    assert cif_card.stop() == 0 and not cif_card.running


@pytest.mark.cif_network({"node": [{"id": 1}, {"id": 2, "sim": {"silent": True}}]})
def test_waiting_for_a_node_that_never_answers_names_it(cif_card: CifCard) -> None:
    """Node 1 in data exchange first, waited for as a condition: the wait's own time-out
    can then be short, with only the node that never answers left to name."""
    wait_until(lambda: 1 in cif_card.diagnostics().operating(), 30, "node 1 in data exchange")
    with pytest.raises(CardError, match=r"node\(s\) \[2\] not in data exchange"):
        cif_card.wait_until_operating(timeout=0.5)
    assert 1 in cif_card.diagnostics().operating()


@pytest.mark.cif_network({"node": [{"id": 4}]}, configure=False)
def test_a_card_can_be_left_for_the_program_to_configure(cif_card: CifCard) -> None:
    """configure=False: the nodes are simulated, but the card waits, unconfigured, for a
    host that configures it, as legacy programs do; here `cifemu configure` is that host."""
    diag = cif_card.diagnostics()
    assert diag.configured() == [] and diag.can_state_name == "OFFLINE"
    assert cif_card.network is not None and cif_card.network.path is not None
    done = commands.run([sys.executable, "-m", "cifemu", "configure",
                         str(cif_card.network.path), "--board", "0", "--wait", "0"],
                        capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert cif_card.wait_until_operating().operating() == [4]
    assert "online_configure" not in cif_card.log.read_text()  # the card's own host never ran


def test_a_card_without_a_network_says_how_to_give_one(cif_card: CifCard) -> None:
    assert cif_card.network is None and cif_card.running
    with pytest.raises(CardError, match=r"@pytest\.mark\.cif_network"):
        cif_card.wait_until_operating()


def test_a_network_dict_is_written_as_the_toml_it_stands_for() -> None:
    description = {
        "bus": {"bitrate": 250_000, "auto_clear": True},
        "node": [{"id": 5, "name": 'quote " backslash \\ tab \t del \x7f é',
                  "boot": ["reset", "start"],
                  "pdo": [{"direction": "output", "cob_id": 0x205}],
                  "sim": {"sdo_abort": {"6200:1": 0x06090011}, "boot_delay_s": 0.25,
                          "emcy_burst": {"after_s": 1e-3}}}],
    }
    assert tomllib.loads(network_toml(description)) == description


def test_the_guides_code_is_the_examples_code() -> None:
    """docs/pytest-plugin.md shows the example files as they are in examples/pytest/, whose
    run above proves them: every longer block of it is part of one of them."""
    guide = (ROOT / "docs" / "pytest-plugin.md").read_text()
    sources = [path.read_text() for path in EXAMPLES.glob("*.py")]
    blocks = [block for block in re.findall(r"```python\n(.*?)```", guide, re.S)
              if block.count("\n") > 8]
    assert len(blocks) == 3
    stale = [block for block in blocks if not any(block in source for source in sources)]
    assert not stale, f"blocks of the guide that no example holds as written: {stale}"
