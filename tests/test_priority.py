"""Real-time loop processes ask for a lower nice value (when permitted), configurable by UNIROS_LOOP_NICE."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from uniros_async.priority import DEFAULT_LOOP_NICE, loop_nice


def test_loop_nice_parsing(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("UNIROS_LOOP_NICE", raising=False)
    assert loop_nice() == DEFAULT_LOOP_NICE
    monkeypatch.setenv("UNIROS_LOOP_NICE", "-5")
    assert loop_nice() == -5
    monkeypatch.setenv("UNIROS_LOOP_NICE", "off")
    assert loop_nice() is None
    for bad in ("fast", "-21", "20"):
        monkeypatch.setenv("UNIROS_LOOP_NICE", bad)
        with pytest.raises(ValueError, match="UNIROS_LOOP_NICE must be an integer in \\[-20, 19\\] or 'off'"):
            loop_nice()


@pytest.mark.parametrize("setting", ["-3", "off"])
def test_raise_loop_priority_in_a_child(setting: str) -> None:
    """In a fresh process: nice is lowered to the setting when permitted, left alone when 'off' or not permitted."""
    code = "import os; from uniros_async.priority import raise_loop_priority as r; print(r(), os.getpriority(0, 0))"
    env = {**os.environ, "UNIROS_LOOP_NICE": setting}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60, check=True)
    changed, nice = out.stdout.split()
    base = os.getpriority(os.PRIO_PROCESS, 0)
    if setting == "off":
        assert (changed, int(nice)) == ("False", base)
    elif os.geteuid() == 0:  # root may lower nice
        assert (changed, int(nice)) == (str(base > -3), min(base, -3))
    else:  # not permitted: keeps its priority, no error
        assert int(nice) == base
