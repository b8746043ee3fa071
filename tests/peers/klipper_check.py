#!/usr/bin/env python3
"""Check a Klipper G-code file against what Klipper's own host code (klippy, batch mode)
made of it. Fails (exit 1) unless:

1. klippy's log holds no error (`!!`, a refused MANUAL_STEPPER, a step compression
   error);
2. each syringe's net steps equal the file's plunger travel (summed over its jobs), to
   1 step plus 2e-8 of the travel: klippy keeps positions as doubles, and over the
   femur's 2.9 million moves (190 million steps) they drift by about 2 steps;
3. in sync: at the last step of every block of syringe steps klippy queued (and of
   X/Y blocks, at most --samples in all), every stepper's position lies on the file's
   path, on one straight segment between two consecutive lines' end points, to 2 steps
   plus one step of the segment's longest axis scaled to the axis;
4. no syringe runs backwards by more than --max-backward-mm in one run of steps (a
   resumed job whose positions start where the plunger does not stand pulls it back).

usage: klipper_check.py GCODE DUMP LOG [--samples N] [--max-backward-mm MM]
       klipper_check.py --shift-syringe-words GCODE OUT   (the negative control)

DUMP is `python -m klippy.parsedump DICT OUT`. Steppers are found by their step pins
and resolutions in tests/peers/klipper/printer.cfg (PINS below). The file's `G28` is a
straight move to X0 Y0 Z0: the printer.cfg's homing_override makes it one, so that
step counts stay absolute over several jobs.
"""
import argparse
import bisect
import re
import sys

# step pin -> (axis letter, steps per mm), as in tests/peers/klipper/printer.cfg.
PINS = {
    "gpiochip0/gpio0": ("X", 1280.0),
    "gpiochip0/gpio4": ("Y", 1280.0),
    "gpiochip0/gpio8": ("Z", 400.0),
    "gpiochip0/gpio12": ("A", 102400.0),
    "gpiochip0/gpio15": ("B", 102400.0),
    "gpiochip0/gpio18": ("C", 102400.0),
}
SPM = dict(PINS.values())
AXES = ["X", "Y", "Z", "A", "B", "C"]
SYRINGES = ["A", "B", "C"]


def file_path(path):
    """The file's path as points in steps (one per line that moves), and each syringe's
    travel in mm. A syringe's coordinate becomes steps through its offset: SET_POSITION
    changes the coordinate, not where the plunger stands."""
    at = {a: 0.0 for a in AXES}
    offset = {a: 0.0 for a in SYRINGES}
    points = [dict(at)]
    for raw in open(path):
        code = raw.split(";")[0].strip()
        if not code:
            continue
        m = re.match(r"MANUAL_STEPPER STEPPER=syringe_(\w) (SET_POSITION|MOVE)=(\S+)", code)
        if m:
            axis, what, v = m.group(1).upper(), m.group(2), float(m.group(3))
            if what == "SET_POSITION":
                offset[axis] += at[axis] - v
                at[axis] = v
            else:
                at[axis] = v
                points.append(steps_of(at, offset))
            continue
        word = code.split()[0]
        if word == "G28":
            at.update(X=0.0, Y=0.0, Z=0.0)
            points.append(steps_of(at, offset))
        elif word in ("G0", "G1"):
            for w in code.split()[1:]:
                if w[0] in at:
                    at[w[0]] = float(w[1:])
            points.append(steps_of(at, offset))
    travel = {a: (at[a] + offset[a]) for a in SYRINGES if a in used_syringes(points)}
    return points, travel


def steps_of(at, offset):
    return {a: (at[a] + offset.get(a, 0.0)) * SPM[a] for a in AXES}


def used_syringes(points):
    return {a for a in SYRINGES if any(p[a] != 0.0 for p in points)}


class Stepper:
    """One stepper's steps as klippy queued them, with the MCU's step timing
    (stepper.c: a block's first step comes `interval` after the last step, and each
    interval after it grows by `add`)."""

    def __init__(self):
        self.clock = 0
        self.direction = 1
        self.pos = 0
        self.ends = []  # clock of each block's last step
        self.blocks = []  # (clock before the block, interval, count, add, dir, pos before)
        self.longest_backward = 0
        self.backward = 0

    def queue(self, interval, count, add):
        self.blocks.append((self.clock, interval, count, add, self.direction, self.pos))
        self.clock += count * interval + add * count * (count - 1) // 2
        self.pos += self.direction * count
        self.ends.append(self.clock)
        if self.direction < 0:
            self.backward += count
            self.longest_backward = max(self.longest_backward, self.backward)
        else:
            self.backward = 0

    def position_at(self, clock):
        """Position right after every step due at or before `clock`."""
        i = bisect.bisect_left(self.ends, clock)
        if i == len(self.blocks):
            return self.pos
        start, interval, count, add, direction, before = self.blocks[i]
        lo, hi = 0, count  # steps done: the largest n with step n's time <= clock
        while lo < hi:
            n = (lo + hi + 1) // 2
            if start + n * interval + add * n * (n - 1) // 2 <= clock:
                lo = n
            else:
                hi = n - 1
        return before + direction * lo


def read_dump(path):
    """Each stepper's steps. The MCU's clock is 32 bits: a step further than
    CLOCK_DIFF_MAX ticks after the stepper's last goes alone (stepcompress.c,
    stepcompress_flush_far), its interval modulo 2**32 (a stepper idle for more than
    86 s at 50 MHz: Z during a long layer), in a message sent when its time is near.
    serialqueue sends messages in order of the clock they ask for (a block's start; a
    far step's own time), so a lone step's time is the one nearest the latest block
    start sent before it."""
    steppers, axis_of = {}, {}
    latest = 0
    for line in open(path):
        if line.startswith("queue_step "):
            oid, interval, count, add = (int(v) for v in re.findall(r"=(-?\d+)", line)[:4])
            s = steppers.get(str(oid))
            if s is None:
                continue
            if count == 1:
                # A far step's interval may wrap to any value: its time is the one
                # nearest the latest block start sent before it.
                while s.clock + interval < latest - (1 << 31):
                    interval += 1 << 32
            latest = max(latest, s.clock)
            s.queue(interval, count, add)
            continue
        m = re.match(r"set_next_step_dir oid=(\d+) dir=(\d+)", line)
        if m and m.group(1) in steppers:
            steppers[m.group(1)].direction = 1 if m.group(2) == "1" else -1
            continue
        m = re.match(r"reset_step_clock oid=(\d+) clock=(\d+)", line)
        if m and m.group(1) in steppers:
            steppers[m.group(1)].clock = int(m.group(2))
            continue
        m = re.match(r"config_stepper oid=(\d+) step_pin=(\S+)", line)
        if m and m.group(2) in PINS:
            steppers[m.group(1)] = Stepper()
            axis_of[m.group(1)] = PINS[m.group(2)][0]
    return {axis_of[o]: s for o, s in steppers.items()}


def on_segment(p, a, b):
    """Whether point `p` lies on the segment a-b (all in steps), within tolerance."""
    deltas = {k: b[k] - a[k] for k in p}
    lead = max(deltas, key=lambda k: abs(deltas[k]))
    span = abs(deltas[lead])
    if span < 1.0:
        return all(min(a[k], b[k]) - 2 <= p[k] <= max(a[k], b[k]) + 2 for k in p)
    s = (p[lead] - a[lead]) / deltas[lead]
    if s < -2 / span or s > 1 + 2 / span:
        return False
    s = min(max(s, 0.0), 1.0)
    return all(
        abs(a[k] + s * deltas[k] - p[k]) <= 2 + abs(deltas[k]) / span for k in p
    )


def check_sync(points, steppers, samples):
    """Walk klippy's positions at sample times along the file's path; the first
    position off it, or None."""
    clocks = set()
    for axis in SYRINGES + ["X", "Y"]:
        if axis in steppers:
            clocks.update(steppers[axis].ends)
    clocks = sorted(clocks)
    stride = max(1, len(clocks) // samples)
    axes = [a for a in AXES if a in steppers]
    k = 1
    checked = 0
    for clock in clocks[::stride]:
        p = {a: steppers[a].position_at(clock) for a in axes}
        start = k
        while k < len(points) and not on_segment(p, points[k - 1], points[k]):
            k += 1
        if k == len(points):
            near = {a: round(points[start][a]) for a in axes}
            return (f"at clock {clock} klippy stands at {p}, on no segment of the file's "
                    f"path from line-end point {start} ({near}) on")
        checked += 1
    return None, checked


def shift_syringe_words(src, dst):
    """The negative control: each line that moves X or Y takes the syringe words of the
    next such line (the last keeps its own), so the plungers run one line early and end
    where the file's do: the net steps match, the sync check must fail."""
    lines = open(src).read().split("\n")
    xy = [i for i, l in enumerate(lines)
          if l.startswith("G1 ") and any(w[0] in "XY" for w in l.split()[1:])]
    words = [[w for w in lines[i].split(";")[0].split()[1:] if w[0] in SYRINGES] for i in xy]
    for n, i in enumerate(xy[:-1]):
        code, _, comment = lines[i].partition(";")
        kept = [w for w in code.split() if w[0] not in SYRINGES]
        lines[i] = " ".join(kept[:1] + [w for w in kept[1:] if w[0] != "F"] + words[n + 1]
                            + [w for w in kept[1:] if w[0] == "F"])
        if comment:
            lines[i] += " ;" + comment
    open(dst, "w").write("\n".join(lines))


def main():
    if len(sys.argv) == 4 and sys.argv[1] == "--shift-syringe-words":
        shift_syringe_words(sys.argv[2], sys.argv[3])
        return 0
    ap = argparse.ArgumentParser()
    ap.add_argument("gcode")
    ap.add_argument("dump")
    ap.add_argument("log")
    ap.add_argument("--samples", type=int, default=1_000_000)
    ap.add_argument("--max-backward-mm", type=float, default=None)
    args = ap.parse_args()
    name = args.gcode
    errors = [
        l.strip()
        for l in open(args.log, errors="replace")
        if l.startswith("!!") or "Invalid sequence" in l or "Must unregister" in l
        or "Internal error" in l or "Error on" in l or "not valid for" in l
    ]
    if errors:
        print(f"{name}: klippy reported errors: {errors[:5]}")
        return 1
    points, travel = file_path(args.gcode)
    steppers = read_dump(args.dump)
    bad = not travel
    for axis in sorted(travel):
        want = travel[axis] * SPM[axis]
        got = steppers[axis].pos if axis in steppers else 0
        ok = abs(got - round(want)) <= 1 + 2e-8 * abs(want)
        bad |= not ok
        print(f"{name}: syringe {axis}: file {travel[axis]:.6f} mm = {round(want)} steps, "
              f"klippy {got} steps {'ok' if ok else 'WRONG'}")
    result = check_sync(points, steppers, args.samples)
    if isinstance(result, str):
        print(f"{name}: OUT OF SYNC: {result}")
        bad = True
    else:
        print(f"{name}: in sync with the file's path at {result[1]} sample times "
              f"({len(points)} line-end points)")
    for axis in sorted(travel):
        back_mm = steppers[axis].longest_backward / SPM[axis] if axis in steppers else 0
        limit = args.max_backward_mm
        ok = limit is None or back_mm <= limit
        bad |= not ok
        print(f"{name}: syringe {axis}: longest backward run {back_mm:.6f} mm"
              + ("" if limit is None else f" (at most {limit} mm) {'ok' if ok else 'WRONG'}"))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
