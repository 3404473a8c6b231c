"""Every parser of outside bytes gets a sample of generated inputs on every run (the 100,000-input runs are
``python -m rig.fuzz --parser all --count 100000``; their table is in docs/reliability.md)."""

from __future__ import annotations

import pytest
from rig import fuzz

SAMPLE = 1500


@pytest.mark.parametrize("parser", list(fuzz.PARSERS))
def test_parser_survives_generated_inputs(parser: str) -> None:
    counts = fuzz.run(parser, SAMPLE, seed=1)
    report = fuzz.format_table([counts])
    assert counts.inputs == SAMPLE
    assert counts.crashes == 0 and counts.hangs == 0, report
    assert counts.accepted > 0, f"not even the valid seeds were accepted:\n{report}"
    assert counts.rejected > 0, f"nothing was rejected: the mutations do not reach the parser:\n{report}"


def test_mutations_are_deterministic_and_varied() -> None:
    import random

    seeds = [b"\x89UNIROS\n" + bytes(44)]
    rng_a, rng_b = random.Random(3), random.Random(3)
    a = [fuzz.mutate(rng_a, seeds) for _ in range(50)]
    b = [fuzz.mutate(rng_b, seeds) for _ in range(50)]
    assert a == b
    assert len(set(a)) > 40
