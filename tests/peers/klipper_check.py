#!/usr/bin/env python3
"""Check a Klipper G-code file against what Klipper's own host code (klippy, batch mode)
made of it: klippy must exit 0 with no error in its log, and each syringe's net steps
must equal the file's final plunger position (summed over its jobs) in steps, +-1.

usage: klipper_check.py GCODE DUMP LOG STEPS_PER_MM

DUMP is `python -m klippy.parsedump DICT OUT`; the syringe steppers are found by their
step pins in tests/peers/klipper/printer.cfg (gpio12: syringe_a, gpio15: syringe_b).
"""
import re
import sys

PINS = {"gpiochip0/gpio12": "A", "gpiochip0/gpio15": "B"}


def file_travel(path):
    """Net plunger travel per axis letter over the file: each job's positions start at 0
    after its `SET_POSITION=0`; travel is the sum of each job's final positions."""
    pos, total = {}, {}
    for raw in open(path):
        code = raw.split(";")[0].strip()
        m = re.match(r"MANUAL_STEPPER STEPPER=syringe_(\w) SET_POSITION=(\S+)", code)
        if m:
            axis = m.group(1).upper()
            total[axis] = total.get(axis, 0.0) + pos.get(axis, 0.0)
            pos[axis] = float(m.group(2))
            continue
        if code.startswith("G1 ") or code.startswith("G0 "):
            for w in code.split()[1:]:
                if w[0] in PINS.values():
                    pos[w[0]] = float(w[1:])
    for axis, p in pos.items():
        total[axis] = total.get(axis, 0.0) + p
    return total


def dump_steps(path):
    """Net steps per syringe axis from klippy.parsedump's output."""
    oid_axis, direction, net = {}, {}, {}
    for line in open(path):
        m = re.match(r"config_stepper oid=(\d+) step_pin=(\S+)", line)
        if m and m.group(2) in PINS:
            oid_axis[m.group(1)] = PINS[m.group(2)]
            continue
        m = re.match(r"set_next_step_dir oid=(\d+) dir=(\d+)", line)
        if m:
            direction[m.group(1)] = 1 if m.group(2) == "1" else -1
            continue
        m = re.match(r"queue_step oid=(\d+) interval=\d+ count=(\d+)", line)
        if m and m.group(1) in oid_axis:
            axis = oid_axis[m.group(1)]
            net[axis] = net.get(axis, 0) + direction.get(m.group(1), 1) * int(m.group(2))
    return net


def main():
    gcode, dump, log, steps_per_mm = sys.argv[1:5]
    steps_per_mm = float(steps_per_mm)
    errors = [
        l.strip()
        for l in open(log, errors="replace")
        if l.startswith("!!") or "Invalid sequence" in l or "Must unregister" in l
        or "Internal error" in l or "Error on" in l
    ]
    if errors:
        print(f"{gcode}: klippy reported errors: {errors[:5]}")
        return 1
    want = file_travel(gcode)
    got = dump_steps(dump)
    bad = False
    for axis in sorted(want):
        w = round(want[axis] * steps_per_mm)
        g = got.get(axis, 0)
        ok = abs(g - w) <= 1
        bad |= not ok
        print(f"{gcode}: syringe {axis}: file {want[axis]:.6f} mm = {w} steps, "
              f"klippy {g} steps {'ok' if ok else 'WRONG'}")
    return 1 if bad or not want else 0


if __name__ == "__main__":
    sys.exit(main())
