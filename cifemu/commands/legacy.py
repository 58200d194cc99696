"""cifemu legacy: run an unchanged legacy binary against the emulated card.

  cifemu legacy [--dpm-dir DIR] -- PROGRAM ARGS...

A legacy program has Hilscher's API object linked in and reaches the card only through
the character device /dev/cif. This command starts it with libcifdev.so preloaded
(LD_PRELOAD), which serves /dev/cif from the card's image in DIR (CIF_DPM_DIR): the
library built for the program's ELF class, i386 or x86-64. A statically linked program
cannot take a preload; it needs a real /dev/cif, which a CUSE device (character device
in user space) would give -- future work, see docs/legacy.md.
"""

from __future__ import annotations

import argparse
import os
import shutil
import struct
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from cifemu import libcif
from dpm.image import DEFAULT_DPM_DIR

PRELOAD_64 = libcif.BUILD / "libcifdev.so"
PRELOAD_32 = libcif.BUILD / "i386" / "libcifdev.so"
MISSING_32 = libcif.BUILD / "i386" / "MISSING"

ELF_MAGIC = b"\x7fELF"
ELFCLASS32, ELFCLASS64 = 1, 2
EM_386, EM_X86_64 = 3, 62
PT_INTERP = 3


class LegacyError(Exception):
    """The program cannot run with the preload; the message says why and what instead."""


@dataclass(frozen=True)
class ElfProgram:
    """What the ELF header says about a program: its class, machine and linking."""

    elf_class: int
    machine: int
    dynamic: bool


def read_elf(path: Path) -> ElfProgram:
    """Parse the ELF header and program headers: class, machine, and whether the
    program names an interpreter (PT_INTERP), which only dynamically linked ones do."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise LegacyError(f"{path}: {exc.strerror}") from exc
    if len(data) < 52 or data[:4] != ELF_MAGIC:
        raise LegacyError(f"{path}: not an ELF program")
    elf_class, order = data[4], data[5]
    if elf_class not in (ELFCLASS32, ELFCLASS64) or order != 1:
        raise LegacyError(f"{path}: not a little-endian 32- or 64-bit ELF program")
    machine = struct.unpack_from("<H", data, 18)[0]
    if elf_class == ELFCLASS32:
        phoff, phentsize, phnum = (struct.unpack_from("<I", data, 28)[0],
                                   *struct.unpack_from("<HH", data, 42))
    else:
        if len(data) < 64:
            raise LegacyError(f"{path}: truncated ELF header")
        phoff, phentsize, phnum = (struct.unpack_from("<Q", data, 32)[0],
                                   *struct.unpack_from("<HH", data, 54))
    dynamic = False
    for index in range(phnum):
        offset = phoff + index * phentsize
        if phentsize < 4 or offset + 4 > len(data):
            raise LegacyError(f"{path}: truncated program headers")
        if struct.unpack_from("<I", data, offset)[0] == PT_INTERP:
            dynamic = True
    return ElfProgram(elf_class, machine, dynamic)


def preload_for(program: ElfProgram, path: Path) -> Path:
    """The libcifdev.so of the program's ABI, built when missing."""
    if not program.dynamic:
        raise LegacyError(
            f"{path} is statically linked: LD_PRELOAD cannot reach it. It needs a real "
            "/dev/cif, which a CUSE device would provide (not implemented yet; see "
            "docs/legacy.md)")
    if program.elf_class == ELFCLASS32 and program.machine == EM_386:
        wanted = PRELOAD_32
    elif program.elf_class == ELFCLASS64 and program.machine == EM_X86_64:
        wanted = PRELOAD_64
    else:
        raise LegacyError(f"{path}: ELF machine {program.machine} is neither i386 nor x86-64")
    if not wanted.exists():
        try:
            libcif.build("preload")
        except libcif.LibcifError as exc:
            raise LegacyError(str(exc)) from exc
    if not wanted.exists():
        reason = MISSING_32.read_text().strip() if MISSING_32.exists() else "build failed"
        raise LegacyError(f"no {wanted}: {reason}")
    return wanted


def resolve(command: str) -> str:
    """PROGRAM as execvp finds it, and as env, sudo and strace take it: a name with a slash
    is the path itself, kept as given (a Path would make ./prog a bare name, which the
    exec then looked up on $PATH); only a bare name is looked up on $PATH."""
    if "/" in command:
        if not os.path.exists(command):
            raise LegacyError(f"{command}: No such file or directory")
        return command
    found = shutil.which(command)
    if found is None:
        raise LegacyError(f"{command}: not found on $PATH (give ./{command} for a program "
                          "in this directory)")
    return found


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--dpm-dir", default=None, metavar="DIR",
                        help=f"the cards' image directory (default $CIF_DPM_DIR or "
                             f"{DEFAULT_DPM_DIR})")
    parser.add_argument("program", nargs=argparse.REMAINDER,
                        help="-- PROGRAM ARGS...: the legacy program and its arguments")


def run(args: argparse.Namespace) -> int:
    command = list(args.program)
    if command and command[0] == "--":
        command = command[1:]
    if not command:
        print("cifemu legacy: no program given (cifemu legacy -- PROGRAM ARGS...)",
              file=sys.stderr)
        return 2
    try:
        program = resolve(command[0])
        path = Path(program)
        preload = preload_for(read_elf(path), path)
    except LegacyError as exc:
        print(f"cifemu legacy: {exc}", file=sys.stderr)
        return 1
    directory = args.dpm_dir or os.environ.get("CIF_DPM_DIR") or str(DEFAULT_DPM_DIR)
    env = dict(os.environ)
    env["CIF_DPM_DIR"] = str(Path(directory).resolve())
    env["LD_PRELOAD"] = " ".join(filter(None, [str(preload), env.get("LD_PRELOAD", "")]))
    try:
        done = subprocess.run([program, *command[1:]], env=env, check=False)
    except OSError as exc:
        print(f"cifemu legacy: {program}: {exc.strerror}", file=sys.stderr)
        return 1
    return done.returncode if done.returncode >= 0 else 128 - done.returncode
