"""cifemu libcif: compiler and linker flags for C programs (libcif).

  cifemu libcif --cflags --libs     flags that compile a legacy program against libcif:
                                    cc app.c $(cifemu libcif --cflags --libs)

With neither flag it prints the shared library's path. The library is built from
libcif/ of this clone (make -C libcif) when it is missing.
"""

from __future__ import annotations

import argparse
import sys

from cifemu.libcif import SHARED, LibcifError, build, flags


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cflags", action="store_true", help="print the compiler flags")
    parser.add_argument("--libs", action="store_true", help="print the linker flags")


def run(args: argparse.Namespace) -> int:
    try:
        if not SHARED.exists():
            build()
    except LibcifError as exc:
        print(f"cifemu libcif: {exc}", file=sys.stderr)
        return 1
    print(flags(args.cflags, args.libs) if args.cflags or args.libs else SHARED)
    return 0
