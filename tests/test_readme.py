"""The README does what it says: its Python examples run as written, its commands and links exist, and a reader
meets the commands, an example and the docs early (CI greps the ``# tests`` line and runs it verbatim)."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)
BLOCKS = [
    (lang, body, README[: m.start()].count("\n") + 1) for m in FENCE.finditer(README) for lang, body in [m.groups()]
]
PYTHON = [(body, line) for lang, body, line in BLOCKS if lang == "python"]
SHELL = [body for lang, body, _ in BLOCKS if lang == "sh"]


@pytest.mark.slow
@pytest.mark.parametrize(("code", "line"), PYTHON, ids=[f"line{line}" for _, line in PYTHON])
def test_python_example_runs_as_written(code: str, line: int, tmp_path: Path) -> None:
    # Written to a file and run as a script, as a reader would (make_vec's workers need a main module to spawn from).
    script = tmp_path / "example.py"
    script.write_text(code)
    done = subprocess.run(
        [sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=180, check=False
    )
    assert done.returncode == 0, f"README.md line {line}:\n{done.stderr[-3000:]}"
    assert done.stdout.strip(), f"README.md line {line} printed nothing"


def test_the_two_commands_come_first() -> None:
    lines = README.splitlines()
    first_block = lines[lines.index("```sh") + 1 : lines.index("```sh") + 3]
    assert first_block[0].endswith("# main job") and "uniros bench latency" in first_block[0]
    assert first_block[1].endswith("# tests") and "python -m pytest" in first_block[1]
    assert lines.index("```sh") < 5


def test_a_newcomer_meets_an_example_and_the_docs_early() -> None:
    lines = README.splitlines()
    first_python = next(i for i, line in enumerate(lines, 1) if line == "```python")
    first_doc_link = next(i for i, line in enumerate(lines, 1) if "](docs/" in line)
    assert first_python + len(PYTHON[0][0].splitlines()) <= 40, "the first example ends within 40 lines"
    assert first_doc_link < 80


def test_shell_blocks_are_copy_paste_safe() -> None:
    for body in SHELL:
        for line in body.splitlines():
            command = line.split("  #")[0]
            assert "|" not in command, f"a pipe in the README's shell block: {line!r}"
            shlex.split(command)  # balanced quotes


def test_linked_files_and_named_configs_exist() -> None:
    for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", README):
        assert (ROOT / target).exists(), f"README links to a missing {target}"
    for path in re.findall(r"\b(configs/[\w./-]+\.yaml)\b", README):
        assert (ROOT / path).is_file(), f"README names a missing {path}"


def test_uniros_commands_in_shell_blocks_parse() -> None:
    commands = {
        tuple(words[1:3])
        for body in SHELL
        for line in body.splitlines()
        if (words := shlex.split(line.split("  #")[0].split("&&")[-1]))[:1] == ["uniros"]
    }
    assert ("bench", "latency") in commands
    for command in sorted(commands):
        words = [w for w in command if not w.startswith("-") and "/" not in w and "." not in w]
        done = subprocess.run(
            [sys.executable, "-m", "uniros_async.cli", *words, "--help"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        assert done.returncode == 0, f"uniros {' '.join(words)} --help: {done.stderr[-2000:]}"
