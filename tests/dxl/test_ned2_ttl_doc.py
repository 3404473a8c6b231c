"""docs/dynamixel.md's "The Ned2's TTL bus": the stepper's register table is well formed, its list of what the
stepper lacks covers every X-series register the bus arm uses (so the verdict follows the arm's needs as they
change), and the Ned2 has no servo map, as the section says."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

from uniros_async.hardware.dxl import arm as arm_module
from uniros_async.hardware.dxl import control_table as ct
from uniros_async.hardware.dxl.servo_map import RX200_SERVOS, servo_map_names
from uniros_async.robots import get_robot_spec

DOC = Path(__file__).resolve().parents[2] / "docs" / "dynamixel.md"


def _ned2_section() -> str:
    doc = DOC.read_text()
    assert "\n## The Ned2's TTL bus\n" in doc
    return doc.split("\n## The Ned2's TTL bus\n", 1)[1].split("\n## ", 1)[0]


def _table(heading: str) -> list[list[str]]:
    """The cells of the first table under ``### heading`` in the Ned2 section (header and rule left out)."""
    part = _ned2_section().split(f"\n### {heading}\n", 1)[1].split("\n### ", 1)[0]
    lines = part.splitlines()
    first = next(i for i, ln in enumerate(lines) if ln.startswith("|"))
    block = []
    for ln in lines[first:]:
        if not ln.startswith("|"):
            break
        block.append(ln)
    rows = [[c.strip() for c in ln.strip().strip("|").split("|")] for ln in block[2:]]
    assert rows, heading
    return rows


def _stepper_registers() -> dict[int, tuple[int, str, int]]:
    """address -> (size, ned_ros name, header line)."""
    out: dict[int, tuple[int, str, int]] = {}
    for address, size, name, *_, line in _table("The stepper's registers"):
        out[int(address)] = (int(size), name, int(line))
    return out


def _lacking() -> dict[str, tuple[int, int]]:
    """X-series register name -> (address, size), from the table of what the stepper lacks."""
    out: dict[str, tuple[int, int]] = {}
    for names, address, size, on_stepper, _ in _table("What is missing, and what follows"):
        assert on_stepper == "none", names
        for name in names.split(" / "):
            out[name] = (int(address), int(size))
    return out


def _x_register(name: str) -> ct.Register:
    for table in (ct.XM430_W350, ct.XL430_W250, ct.XL330_M288):
        if name in table:
            return table.register(name)
    raise AssertionError(f"{name} is in no X-series table")


def test_the_stepper_table_is_in_address_order_without_overlaps() -> None:
    regs = _stepper_registers()
    addresses = list(regs)
    assert addresses == sorted(addresses) and len(set(addresses)) == len(addresses)
    assert regs[0][:2] == (2, "MODEL_NUMBER")
    for here, after in zip(addresses, addresses[1:], strict=False):
        size, name, line = regs[here]
        assert size in (1, 2, 4), name
        assert here + size <= after, f"{name} ({here}, {size} bytes) runs into {regs[after][1]} ({after})"
        assert line < regs[after][2], f"{name}: the header's lines follow its addresses"


def test_what_the_stepper_lacks_covers_every_register_the_bus_arm_uses() -> None:
    x_names = set(ct.XM430_W350.registers) | set(ct.XL430_W250.registers)
    used = set(RX200_SERVOS.eeprom(RX200_SERVOS.servos[0]))
    used |= set(re.findall(r'"([a-z_0-9]+)"', inspect.getsource(arm_module))) & x_names
    address, length = arm_module.STATE_BLOCK
    for table in (ct.XM430_W350, ct.XL430_W250):
        used |= {r.name for r in table.registers.values() if address <= r.address < address + length}
    assert {"bus_watchdog", "goal_position", "present_position", "drive_mode"} <= used

    stepper, lacking = _stepper_registers(), _lacking()
    for name in sorted(used):
        reg = _x_register(name)
        same_place = stepper.get(reg.address, (0, "", 0))[0] == reg.size
        if same_place:
            assert name not in lacking, f"{name}: the stepper table has it at {reg.address}, the doc says it lacks it"
        else:
            assert lacking.get(name) == (reg.address, reg.size), (
                f"{name} ({reg.address}, {reg.size} bytes) is used by the bus arm and is not in the stepper's table: "
                "the doc's list of what the stepper lacks must name it"
            )
    for name, (addr, size) in lacking.items():
        reg = _x_register(name)
        assert (reg.address, reg.size) == (addr, size), name
        assert stepper.get(addr, (0, "", 0))[0] != size, f"{name}: listed as lacking, but the stepper has {addr}"


def test_the_ned2_has_no_servo_map_and_its_bus_names_every_joint() -> None:
    assert "ned2" not in servo_map_names()
    joints = set()
    for ids, device, *_ in _table("The bus"):
        assert re.fullmatch(r"\d+(, \d+)*", ids), ids
        joints |= set(re.findall(r"joint_\d", device))
    assert joints == set(get_robot_spec("ned2").arm_joint_names)
