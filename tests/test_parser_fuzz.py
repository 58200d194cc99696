"""Hostile input for the parsers a user feeds by hand: the network TOML, EDS/DCF files, and
the command line. Only the documented errors come out (``NetworkError``, ``EdsError`` and
``BuildError``, all ``DbmError``s, or a command's exit status with a message that names the
file), never a traceback.

The normal run is a few seconds; CIFEMU_FUZZ_EXAMPLES=100000 makes a dedicated long run.
"""

from __future__ import annotations

import contextlib
import io
import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from cifemu.cli import main as cifemu_main
from dbm_tools.builder import build_dbm
from dbm_tools.container import write_dbm
from dbm_tools.errors import DbmError
from dbm_tools.network import NetworkError, load_network
from tests.conftest import ROOT

EXAMPLES = int(os.environ.get("CIFEMU_FUZZ_EXAMPLES", "300"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=False,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])

DEMO = (ROOT / "cifemu" / "examples" / "demo.toml").read_text()
EDS = (ROOT / "tests" / "data" / "sim_io.eds").read_text()
TOML_WORDS = ["[bus]", "[[node]]", "[node.sim]", "[[node.pdo]]", "[[node.sdo]]", "id = ",
              "bitrate = ", "sync_period_ms = ", "eds = ", "transmission = ", "cob_id = ",
              "direction = ", "boot = ", "heartbeat_ms = ", "error_control = ", "\"", "[",
              "]", "{", "}", "=", ",", "\n", "0x", "-1", "1e9", "true", "\"output\"", "255"]


def mutate(text: str, data: st.DataObject) -> str:
    """``text`` with a few lines deleted, duplicated, cut or replaced by drawn junk."""
    lines = text.splitlines()
    for _ in range(data.draw(st.integers(1, 4))):
        if not lines:
            break
        at = data.draw(st.integers(0, len(lines) - 1))
        kind = data.draw(st.sampled_from(["delete", "duplicate", "cut", "junk", "word"]))
        if kind == "delete":
            del lines[at]
        elif kind == "duplicate":
            lines.insert(at, lines[at])
        elif kind == "cut":
            lines[at] = lines[at][: data.draw(st.integers(0, len(lines[at])))]
        elif kind == "junk":
            lines[at] = data.draw(st.text(max_size=40))
        else:
            lines[at] += data.draw(st.sampled_from(TOML_WORDS)) + data.draw(
                st.text(alphabet="0123456789abcxyz_.\"=[] ", max_size=12))
    return "\n".join(lines) + "\n"


def build(path: Path) -> None:
    """What ``cifemu dbm build`` does with a description: load it, then make the DBM."""
    build_dbm(load_network(path))


@FUZZ
@given(data=st.data())
@example(data=None)  # the unchanged demo builds
def test_network_descriptions_fail_only_with_the_documented_error(
        tmp_path: Path, data: st.DataObject | None) -> None:
    path = tmp_path / "net.toml"
    path.write_text(DEMO if data is None else mutate(DEMO, data))
    try:
        build(path)
    except DbmError as exc:
        assert str(exc)  # NetworkError / BuildError say what is wrong


@FUZZ
@given(text=st.text(max_size=300))
def test_any_text_as_a_network_description(tmp_path: Path, text: str) -> None:
    path = tmp_path / "net.toml"
    path.write_text(text)
    with contextlib.suppress(DbmError):
        build(path)


@FUZZ
@given(data=st.one_of(st.binary(max_size=400),
                      st.builds(lambda head, tail: head + tail,
                                st.sampled_from([b"DBMFILE  \0", b"\xff\xfe", b"\xfe\xff",
                                                 b"\xef\xbb\xbf", b"[FileInfo]\n", b""]),
                                st.binary(max_size=200)),
                      st.text(max_size=200).map(lambda text: text.encode("utf-16"))))
@example(data=b"\xd2")
def test_any_bytes_as_a_network_description(tmp_path: Path, data: bytes) -> None:
    """A file of any bytes -- a DBM, UTF-16 text, an EDS, junk -- loads or raises
    NetworkError with a reason; never UnicodeDecodeError or another exception."""
    path = tmp_path / "net.toml"
    path.write_bytes(data)
    try:
        load_network(path)
    except NetworkError as exc:
        assert str(exc)


def test_a_dbm_given_as_a_network_description_is_named_by_every_command(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The SyCon user's most natural mix-up: plant.dbm where NETWORK.toml goes. Each command
    that takes a description says what the file is and which command takes it (it ended
    in a UnicodeDecodeError traceback)."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("CIF_DPM_DIR", str(tmp_path / "no-card"))
    dbm = tmp_path / "plant.dbm"
    dbm.write_bytes(write_dbm(build_dbm(load_network(ROOT / "cifemu" / "examples" / "demo.toml"))))
    for command in (["configure", str(dbm)],
                    ["sim", str(dbm), "--interface", "virtual", "--channel", "x"],
                    ["firmware", "--simulate", str(dbm), "--dpm-dir", str(tmp_path / "dpm")],
                    ["dbm", "build", str(dbm), "-o", str(tmp_path / "out.dbm")]):
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            status = cifemu_main(command)
        assert status == 1, command
        text = err.getvalue()
        assert "SyCon DBM database" in text and f"cifemu dbm download {dbm}" in text, text
        assert len(text.strip().splitlines()) == 1, text


def test_a_utf16_description_says_to_save_it_as_utf8(tmp_path: Path) -> None:
    path = tmp_path / "net.toml"
    path.write_bytes("[[node]]\nid = 5\n".encode("utf-16"))
    with pytest.raises(NetworkError, match=r"UTF-16.*save it as UTF-8"):
        load_network(path)


@settings(FUZZ, max_examples=max(EXAMPLES // 3, 20))
@given(data=st.data())
def test_eds_files_fail_only_with_the_documented_error(tmp_path: Path,
                                                       data: st.DataObject) -> None:
    (tmp_path / "io.eds").write_text(mutate(EDS, data))
    path = tmp_path / "net.toml"
    path.write_text('[[node]]\nid = 5\neds = "io.eds"\n')
    try:
        build(path)
    except DbmError as exc:
        assert str(exc)


SAFE_COMMANDS = [["dbm", "show"], ["dbm", "check"], ["dbm", "build"], ["dbm", "diff"],
                 ["dbm", "dir"], ["dbm", "upload"], ["dbm", "delete"], ["status"],
                 ["configure"], ["libcif"], ["309", "exec"]]
"""Commands that end by themselves whatever their arguments (no server, no live view)."""
ARG_WORDS = ["--json", "--board", "--dpm-dir", "-o", "--name", "--reset", "--cflags",
             "--libs", "--port", "--host", "--wait", "-1", "0", "9", "x", "", "net.toml",
             "missing.dbm", "--", "--no-such-option"]


@settings(FUZZ, max_examples=max(EXAMPLES // 3, 20))
@given(command=st.sampled_from(SAFE_COMMANDS),
       args=st.lists(st.one_of(st.sampled_from(ARG_WORDS), st.text(max_size=8)), max_size=5))
def test_command_lines_end_with_a_status_never_a_traceback(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, command: list[str],
        args: list[str]) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("CIF_DPM_DIR", str(tmp_path / "no-card"))
    (tmp_path / "net.toml").write_text("[[node]]\nid = 1\n[node.x\n")
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            status = cifemu_main([*command, *args])
        except SystemExit as exc:  # argparse: usage and exit status 2, or --help's 0
            status = exc.code if isinstance(exc.code, int) else 1
    assert isinstance(status, int)
    assert "Traceback" not in err.getvalue() + out.getvalue()


def test_a_nul_byte_in_an_argument_is_a_usage_error_not_a_traceback(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The case hypothesis found: ``dbm diff`` opened a path holding a NUL byte and ended
    in pathlib's ValueError."""
    monkeypatch.chdir(tmp_path)
    err = io.StringIO()
    with (contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()),
          pytest.raises(SystemExit) as exit_info):
        cifemu_main(["dbm", "diff", "\x00", "-1"])
    assert exit_info.value.code == 2
    assert "NUL byte" in err.getvalue() and "Traceback" not in err.getvalue()


def test_a_bad_description_is_named_with_its_reason(tmp_path: Path) -> None:
    """The command line says which file and what is wrong with it."""
    bad = tmp_path / "plant.toml"
    bad.write_text("[[node]]\nid = \"five\"\n")
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        status = cifemu_main(["dbm", "build", str(bad), "-o", str(tmp_path / "out.dbm")])
    assert status == 1
    assert "plant.toml" in err.getvalue() and "expected int" in err.getvalue()
