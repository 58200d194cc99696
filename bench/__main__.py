"""``python -m bench [NAME ...]``: run benchmarks, print one JSON list of their results.

Without a name every benchmark runs, in the order below. ``--count`` and
``--warmup`` override each benchmark's own defaults. ``--load`` runs them beside
two busy processes (``bench.load``; ``--busy N`` for another number), and each
result then says so under ``"load"``. ``--quick`` runs the short form of a benchmark
that has one (``scaling``).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from typing import Any

from bench import (
    can,
    cia309,
    dbm,
    exchange_io,
    hops,
    idle,
    lss,
    mailbox,
    remote,
    scaling,
    soak,
    tap,
)
from bench.common import BenchError, add_size_arguments, emit, help_text, progress
from bench.load import DEFAULT_BUSY, busy_load, describe

Runner = Callable[[int | None, int | None], dict[str, Any]]

BENCHMARKS: dict[str, Runner] = {
    mailbox.NAME: mailbox.run,
    exchange_io.NAME: exchange_io.run,
    dbm.NAME: dbm.run,
    can.NAME: can.run,
    cia309.NAME: cia309.run,
    lss.NAME: lss.run,
    idle.NAME: idle.run,
    hops.NAME: hops.run,
    remote.NAME: remote.run,
    scaling.NAME: scaling.run,
    tap.NAME: tap.run,
}

QUICK: dict[str, Runner] = {scaling.NAME: scaling.run_quick}
"""The short forms (``--quick``) of the benchmarks that have one."""


def main(argv: list[str] | None = None) -> int:
    if (code := soak.dispatch(argv)) is not None:
        return code
    parser = argparse.ArgumentParser(prog="python -m bench", description=help_text(__doc__))
    parser.add_argument("names", nargs="*", metavar="NAME",
                        help=f"benchmarks to run: {', '.join(BENCHMARKS)} (default: all)")
    add_size_arguments(parser, "default: each benchmark's own", "default: each benchmark's own")
    parser.add_argument("--load", action="store_true",
                        help=f"run beside {DEFAULT_BUSY} busy processes (issue 22's load)")
    parser.add_argument("--busy", type=int, default=DEFAULT_BUSY, metavar="N",
                        help=f"busy processes for --load (default {DEFAULT_BUSY})")
    parser.add_argument("--quick", action="store_true",
                        help=f"the short form of {', '.join(QUICK)} (the others run as usual)")
    args = parser.parse_args(argv)
    unknown = [name for name in args.names if name not in BENCHMARKS]
    if unknown:
        parser.error(f"unknown benchmark {', '.join(unknown)}; choose from {', '.join(BENCHMARKS)}")
    names = args.names or list(BENCHMARKS)
    results = []
    load: AbstractContextManager[list[int]] = busy_load(args.busy) if args.load else nullcontext([])
    with load as busy:
        for name in names:
            progress(f"running {name}")
            runner = QUICK.get(name, BENCHMARKS[name]) if args.quick else BENCHMARKS[name]
            try:
                result = runner(args.count, args.warmup)
            except BenchError as exc:
                print(f"python -m bench: {name}: {exc}", file=sys.stderr)
                return 1
            result["load"] = describe(busy) if args.load else None
            results.append(result)
    emit(results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
