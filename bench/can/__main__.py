"""``python -m bench.can``: the CAN benchmark's phases, one JSON document on stdout."""

from bench.can.document import main

raise SystemExit(main())
