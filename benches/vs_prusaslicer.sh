#!/bin/sh
# edo's full plan against PrusaSlicer's on the same machine, in the same run (issue 33).
#
#   benches/vs_prusaslicer.sh [RUNS]        (default 3 runs of each, alternating)
#
# The part: the shared 3DBenchy.stl (EDO_MESHES, default ../shared/meshes), 0.2 mm
# layers, nozzle 0.4. edo: a growth-ring gradient, r_mach 2, thin_regions = "fill",
# `edoctl plan JOB --gcode FILE --flavor rrf`. PrusaSlicer 2.5 (Debian's package,
# installed if missing): 100 perimeters, no infill, no top or bottom solid layers, no
# skirt, the same layer height and nozzle, so both lay every road as a perimeter-like
# loop. Prints the medians of wall time and peak memory (GNU time), the extrusion moves,
# the metres of road they draw, moves per metre, G-code bytes, and edo / PrusaSlicer.
set -eu
runs=${1:-3}
repo=$(cd "$(dirname "$0")/.." && pwd)
meshes=${EDO_MESHES:-$repo/../shared/meshes}
mesh=$meshes/3DBenchy.stl
[ -f "$mesh" ] || { echo "no $mesh (set EDO_MESHES)" >&2; exit 1; }

need_apt=""
command -v prusa-slicer >/dev/null 2>&1 || need_apt="$need_apt prusa-slicer"
[ -x /usr/bin/time ] || need_apt="$need_apt time"
if [ -n "$need_apt" ]; then
    echo "installing$need_apt" >&2
    apt-get update -qq >&2
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $need_apt >&2
fi

(cd "$repo" && cargo build --release --locked --bin edoctl >&2)
target=${CARGO_TARGET_DIR:-$repo/target}
edoctl=$target/release/edoctl

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
cp "$mesh" "$work/benchy.stl"
cat > "$work/benchy.toml" <<'EOF'
name = "benchy"
[geometry]
mesh = "benchy.stl"
[materials]
names = ["A", "B"]
[gradient]
pattern = "growth-rings"
inner = [1.0, 0.0]
outer = [0.0, 1.0]
[process]
r_mach = 2.0
nozzle = 0.4
layer = 0.2
thin_regions = "fill"
EOF

i=0
while [ "$i" -lt "$runs" ]; do
    /usr/bin/time -f "edo %e %M" -a -o "$work/times" \
        "$edoctl" plan "$work/benchy.toml" --gcode "$work/edo.gcode" --flavor rrf >/dev/null
    /usr/bin/time -f "prusaslicer %e %M" -a -o "$work/times" \
        prusa-slicer --export-gcode --output "$work/ps.gcode" \
        --layer-height 0.2 --first-layer-height 0.2 --nozzle-diameter 0.4 \
        --perimeters 100 --fill-density 0 --top-solid-layers 0 --bottom-solid-layers 0 \
        --skirts 0 --center 100,100 "$work/benchy.stl" >/dev/null 2>&1
    i=$((i + 1))
done

python3 - "$work" <<'EOF'
import math, os, re, statistics, sys

work = sys.argv[1]
times = {}
for line in open(os.path.join(work, "times")):
    f = line.split()
    if len(f) == 3 and f[0] in ("edo", "prusaslicer"):
        times.setdefault(f[0], []).append((float(f[1]), int(f[2]) * 1024))

def moves(path):
    """Extrusion moves (a G1 with X or Y that pushes material), their length in m."""
    x = y = None
    relative = False
    e_abs = 0.0
    n, length = 0, 0.0
    word = re.compile(r"([A-Z])([-+]?[0-9.:]+)")
    for line in open(path, errors="replace"):
        code = line.split(";", 1)[0].strip()
        if not code:
            continue
        if code.startswith("M83"):
            relative = True
        elif code.startswith("M82"):
            relative = False
        elif code.startswith("G92"):
            for k, v in word.findall(code):
                if k == "E":
                    e_abs = float(v)
        if not (code.startswith("G1 ") or code.startswith("G0 ")):
            continue
        w = dict(word.findall(code))
        nx = float(w["X"]) if "X" in w else x
        ny = float(w["Y"]) if "Y" in w else y
        pushes = False
        if "E" in w:
            e = sum(float(p) for p in w["E"].split(":") if p)
            if relative:
                pushes = e > 0
            else:
                pushes = e > e_abs
                e_abs = e
        if pushes and ("X" in w or "Y" in w) and x is not None:
            n += 1
            length += math.hypot(nx - x, ny - y)
        x, y = nx, ny
    return n, length / 1000.0

rows = {}
for name, gcode in (("edo", "edo.gcode"), ("prusaslicer", "ps.gcode")):
    t = times[name]
    n, metres = moves(os.path.join(work, gcode))
    rows[name] = {
        "wall_s": statistics.median(v[0] for v in t),
        "peak_mib": statistics.median(v[1] for v in t) / 2**20,
        "moves": n,
        "road_m": metres,
        "moves_per_m": n / metres if metres else float("nan"),
        "gcode_mb": os.path.getsize(os.path.join(work, gcode)) / 1e6,
    }
keys = ["wall_s", "peak_mib", "moves", "road_m", "moves_per_m", "gcode_mb"]
print(f"3DBenchy, 0.2 mm layers, nozzle 0.4, medians of {len(times['edo'])} runs")
print(f"{'':14}" + "".join(f"{k:>13}" for k in keys))
for name, r in rows.items():
    print(f"{name:14}" + "".join(f"{r[k]:13.2f}" for k in keys))
ratio = {k: rows["edo"][k] / rows["prusaslicer"][k] for k in keys}
print(f"{'edo / prusa':14}" + "".join(f"{ratio[k]:13.2f}" for k in keys))
print("targets (issue 33): moves_per_m <= 1, gcode_mb <= 1.5, wall_s <= 0.5, peak_mib <= 1")
EOF
