"""The README's fenced blocks, and those of the pages that carry its longer examples: what
tests/test_readme.py runs, and where the tests of a newcomer's first steps find the README's
own example network and commands."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from tests.conftest import ROOT

README = ROOT / "README.md"
RUN_PAGES = tuple(ROOT / "docs" / name for name in (
    "commands.md", "host-programs.md", "network-toml.md", "buses.md", "glossary.md"))
"""Pages whose examples were the README's before it became a ten-minute read: they run too."""
NO_RUN = re.compile(r"^<!-- not run by tests/test_readme\.py: (.+) -->$")
RUNNABLE = {"python", "sh"}
BLOCK_TIMEOUT = 120
"""Seconds one block may take; the slowest (the DBM commands) needs a few."""


@dataclass(frozen=True)
class Block:
    """One fenced block of the README: where it starts, its language and its text."""

    page: str
    """The file, relative to the clone: README.md or a page of RUN_PAGES."""
    line: int
    language: str
    code: str
    no_run: str | None
    """Why the block is not run, from the comment before it; None: it runs."""


def readme_blocks() -> list[Block]:
    """The README's blocks first (its first toml block is the example network), then the
    pages'."""
    return [block for path in (README, *RUN_PAGES) for block in page_blocks(path)]


def page_blocks(path: Path) -> list[Block]:
    lines = path.read_text(encoding="utf-8").splitlines()
    page = path.relative_to(ROOT).as_posix()
    blocks = []
    index = 0
    while index < len(lines):
        fence = lines[index]
        if not fence.startswith("```"):
            index += 1
            continue
        end = lines.index("```", index + 1)
        comment = NO_RUN.match(lines[index - 1]) if index else None
        code = "\n".join(lines[index + 1 : end]) + "\n"
        blocks.append(Block(page, index + 1, fence[3:].strip(), code,
                            comment.group(1) if comment else None))
        index = end + 1
    return blocks


BLOCKS = readme_blocks()
NETWORK = next(block.code for block in BLOCKS if block.language == "toml")
"""The README's example network, which its snippets address."""
