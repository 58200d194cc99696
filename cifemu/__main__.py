"""``python -m cifemu COMMAND``: the one entry point, also where no install put ``cifemu``
on PATH (a clone, a test, a benchmark).

The packages below have no ``__main__`` of their own: a command's face composes
``firmware``, ``host_api`` and ``dbm_tools``, and only ``cifemu`` may import them all
(tests/test_layers.py), so ``python -m firmware`` would be a second name for
``python -m cifemu firmware`` that must reach upwards to work.
"""

import sys

from cifemu.cli import main

sys.exit(main())
