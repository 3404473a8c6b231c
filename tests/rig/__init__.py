"""The suite's own test rig: network namespaces and faults, the delaying relay, the fuzzer and bus peers.

Not installed with the package. Tests import it as ``rig.<module>`` (tests/ is on ``sys.path`` and, for the
processes they start, on ``PYTHONPATH``: tests/conftest.py)."""
