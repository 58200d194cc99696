"""The one file the tests take from outside the repository: SyCon's real DBM export.

It is not part of the repository: it lives in the shared folder beside it (as in CI). The
tests that compare our codecs with it skip, naming the path they looked at, when a clone has
no such folder; every other test stands alone.
"""

from __future__ import annotations

from pathlib import Path

import pytest

REAL_DBM = Path(__file__).resolve().parents[2] / "shared" / "fixtures" / "CIF50-profibus-real.dbm"
"""A PROFIBUS card's database written by SyCon (3502 bytes), the container's only witness."""

REAL_DBM_ABSENT = f"needs SyCon's real DBM export, which is not in the repository: no {REAL_DBM}"

needs_real_dbm = pytest.mark.skipif(not REAL_DBM.is_file(), reason=REAL_DBM_ABSENT)
"""Marks a test that reads `REAL_DBM` itself."""


def real_dbm_bytes() -> bytes:
    """The real file's bytes; skips the calling test or fixture when the file is absent."""
    if not REAL_DBM.is_file():
        pytest.skip(REAL_DBM_ABSENT)
    return REAL_DBM.read_bytes()
