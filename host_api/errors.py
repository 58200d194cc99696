"""The root of the exceptions host_api raises.

The ``Dev*`` functions never raise: like the C driver they return a code. What raises
is the Pythonic layer over them, and each of its exceptions derives from
``HostApiError``, so a host program needs one ``except`` for the host side's
refusals: ``CifError`` (``host_api.board``) carries a driver code.
"""

from __future__ import annotations


class HostApiError(Exception):
    """Something the host side could not do; the subclass says what it carries."""
