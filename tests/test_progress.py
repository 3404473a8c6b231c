"""Progress bars written to a file are plain lines, not tqdm's carriage-return redraws."""

from __future__ import annotations

import io
import os
import pty

from uniros_async._progress import LineProgress, progress_bar


def test_a_file_gets_a_few_plain_lines_and_the_final_count() -> None:
    out = io.StringIO()
    bar = progress_bar(total=1000, desc="train", unit="step", file=out, interval_s=3600.0, mininterval=0.1)
    assert isinstance(bar, LineProgress)
    for _ in range(1000):
        bar.update(1)
    bar.set_postfix_str("rx200:80%", refresh=False)
    bar.write("[train] step 1000: rx200 80%")
    bar.close()
    bar.close()
    text = out.getvalue()
    assert "\r" not in text
    assert text.splitlines() == ["[train] step 1000: rx200 80%", text.splitlines()[1]]
    assert text.splitlines()[1].startswith("train: 1000/1000 step (100 %), rx200:80%, ")


def test_lines_come_at_most_once_per_interval() -> None:
    out = io.StringIO()
    bar = progress_bar(total=10, desc="eval", unit="ep", file=out, interval_s=0.0)
    for _ in range(10):
        bar.update(1)
    bar.close()
    lines = out.getvalue().splitlines()
    assert [line.split(",")[0] for line in lines] == [f"eval: {n}/10 ep ({10 * n} %)" for n in range(1, 11)] + [
        "eval: 10/10 ep (100 %)"
    ]


def test_a_terminal_gets_tqdm() -> None:
    leader, follower = pty.openpty()
    try:
        with os.fdopen(follower, "w", closefd=False) as tty:
            bar = progress_bar(total=3, desc="x", unit="s", file=tty)
            assert type(bar).__module__.startswith("tqdm")
            bar.close()
    finally:
        os.close(leader)
        os.close(follower)
