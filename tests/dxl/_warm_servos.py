"""The rx200's servo map for ``uniros robot vbus``, with two more control lines on its stdin for the tests of the
servo readings in an env's info. The vbus process imports this module when it is named as its map
(``servos="dxl._warm_servos:rx200"``); tests/ is on the path of every process the tests start.

``temperature ID C``  sets servo ID's Present_Temperature to C degC (a servo warming up; the sim has no heat)
``get ID NAME``       answers ``ok get ID NAME VALUE``: the register NAME of servo ID as the servo holds it now

Both are answered in the server's own loop, between two bus packets, like the fault lines.
"""

from __future__ import annotations

from uniros_async.errors import ConfigError
from uniros_async.hardware.dxl.vbus_pty import VbusServer

_fault_lines = VbusServer.command


def _command(self: VbusServer, line: str) -> str:
    words = line.split()
    if len(words) == 3 and words[0] in ("temperature", "get"):
        try:
            servo = self._servo(words[1])
            if words[0] == "temperature":
                servo.put("present_temperature", int(words[2], 0))
                return f"ok {line}"
            return f"ok {line} {servo.get(words[2])}"
        except (ValueError, ConfigError) as exc:
            return f"error: {line!r}: {exc}"
    return _fault_lines(self, line)


VbusServer.command = _command  # type: ignore[method-assign]
