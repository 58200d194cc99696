"""Benchmarks of the emulated card: mailbox round trips and process-data exchange.

``python -m bench`` runs them all and prints one JSON list; ``python -m bench NAME``
runs one, as does ``python -m bench.NAME``. Figures go to stdout as JSON, progress
to stderr. Benchmarks measure, they never assert: targets are reported beside the
figures with a ``meets_target`` verdict.
"""
