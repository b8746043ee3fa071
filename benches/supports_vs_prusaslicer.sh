#!/bin/sh
# edo's supports against PrusaSlicer's on the same meshes, in one run (issue 45).
#
#   benches/supports_vs_prusaslicer.sh [PART...]   (default: benchy bracket femur)
#
# Parts: the shared 3DBenchy.stl (EDO_MESHES, default ../shared/meshes) at 0.2 mm,
# nozzle 0.4; benches/bracket-45-70.stl (a 10 mm thick profile with a 45 degree and a
# 70 degree overhang, from vertical) the same; config/examples/femur-graded.toml as it
# is (nozzle 0.8, adaptive 0.2 to 0.6 mm layers; PrusaSlicer at 0.4 mm layers).
# edo: `[support] mode = "everywhere"`, a support syringe S, its default 30 degree
# overhang. PrusaSlicer 2.5: `--support-material --support-material-auto
# --support-material-threshold 60 --support-material-contact-distance 0` (its
# threshold is 90 minus edo's angle; no air gap under the part, as edo's support
# syringe lays it, so both are judged by what the part rests on), 100
# perimeters, no infill, the same nozzle. Both G-codes, with and without supports, are
# checked the same way (examples/gcode_overhangs.rs, the beads of tests/supports.rs):
# the area a layer's beads lay on nothing beyond 30 degrees. Prints, per part, that
# area without and with supports, the support roads' length and volume, and the wall
# time and peak memory (GNU time) of planning with supports to G-code.
set -eu
repo=$(cd "$(dirname "$0")/.." && pwd)
meshes=${EDO_MESHES:-$repo/../shared/meshes}
parts=${*:-benchy bracket femur}

need_apt=""
command -v prusa-slicer >/dev/null 2>&1 || need_apt="$need_apt prusa-slicer"
[ -x /usr/bin/time ] || need_apt="$need_apt time"
if [ -n "$need_apt" ]; then
    echo "installing$need_apt" >&2
    apt-get update -qq >&2
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $need_apt >&2
fi

(cd "$repo" && cargo build --release --locked --bin edoctl --example gcode_overhangs >&2)
target=${CARGO_TARGET_DIR:-$repo/target}
edoctl=$target/release/edoctl
check=$target/release/examples/gcode_overhangs

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

# PrusaSlicer's G-code in the form the check reads: `;LAYER:n Zz` at each `;Z:`,
# relative E, a barrel of 1.75 mm filament.
cat > "$work/from_prusaslicer.py" <<'EOF'
import math, sys
src, dst = sys.argv[1], sys.argv[2]
out = open(dst, "w")
out.write("; barrel area %.6f mm2\n" % (math.pi * 0.875 ** 2))
rel, e, n = False, 0.0, -1
for line in open(src):
    s = line.strip()
    if s.startswith(";Z:"):
        n += 1
        out.write(";LAYER:%d Z%s\n" % (n, s[3:]))
        continue
    if s.startswith(";TYPE:"):
        out.write(s + "\n")
        continue
    code = s.split(";")[0].split()
    if not code:
        continue
    if code[0] == "M83":
        rel = True
    elif code[0] == "M82":
        rel = False
    elif code[0] == "G92":
        for w in code[1:]:
            if w[0] == "E":
                e = float(w[1:])
    elif code[0] in ("G0", "G1"):
        words = []
        for w in code[1:]:
            if w[0] == "E":
                v = float(w[1:])
                words.append("E%.6f" % (v if rel else v - e))
                if not rel:
                    e = v
            elif w[0] in "XY":
                words.append(w)
        out.write("G1 " + " ".join(words) + "\n")
EOF
# Length (mm) and volume (mm3) of the support extrusions of a file from_prusaslicer.py
# wrote (relative E).
cat > "$work/prusaslicer_support.py" <<'EOF'
import math, sys
area = math.pi * 0.875 ** 2
t, x, y, length, volume = "", 0.0, 0.0, 0.0, 0.0
for line in open(sys.argv[1]):
    if line.startswith(";TYPE:"):
        t = line[6:].strip()
        continue
    code = line.split(";")[0].split()
    if not code or code[0] != "G1":
        continue
    nx, ny, de = x, y, 0.0
    for w in code[1:]:
        if w[0] == "X":
            nx = float(w[1:])
        elif w[0] == "Y":
            ny = float(w[1:])
        elif w[0] == "E":
            de = float(w[1:])
    d = math.hypot(nx - x, ny - y)
    if t.startswith("Support") and de > 0 and d > 0:
        length += d
        volume += de * area
    x, y = nx, ny
print("%.0f %.0f" % (length, volume))
EOF
area() { python3 -c "import json,sys; print('%.1f' % json.load(sys.stdin)['unsupported_mm2'])"; }

printf '| part | slicer | on nothing without (mm²) | with (mm²) | support roads (mm) | support road volume (mm³) | wall (s) | peak (MiB) |\n'
printf '|---|---|---|---|---|---|---|---|\n'
for part in $parts; do
    case $part in
    benchy)
        mesh=$meshes/3DBenchy.stl nozzle=0.4 layer=0.2 job_process='layer = 0.2' ;;
    bracket)
        mesh=$repo/benches/bracket-45-70.stl nozzle=0.4 layer=0.2 job_process='layer = 0.2' ;;
    femur)
        mesh=$repo/config/examples/femur.stl nozzle=0.8 layer=0.4 job_process='' ;;
    *) echo "unknown part $part" >&2; exit 2 ;;
    esac
    [ -f "$mesh" ] || { echo "no $mesh (set EDO_MESHES)" >&2; exit 1; }
    if [ "$part" = femur ]; then
        sed "s#^mesh = .*#mesh = \"$mesh\"#" "$repo/config/examples/femur-graded.toml" > "$work/$part.toml"
    else
        cat > "$work/$part.toml" <<EOF
name = "$part"
[geometry]
mesh = "$mesh"
[materials]
names = ["A", "B"]
[gradient]
pattern = "growth-rings"
inner = [1.0, 0.0]
outer = [0.0, 1.0]
[process]
r_mach = 2.0
nozzle = $nozzle
$job_process
thin_regions = "fill"
EOF
    fi
    { cat "$work/$part.toml"; printf '[support]\nmode = "everywhere"\nsyringe = "S"\n'; } > "$work/$part-s.toml"
    plan="plan --quiet --build-volume 300,300,500 --flavor rrf"
    "$edoctl" $plan "$work/$part.toml" --gcode "$work/edo.gcode" >/dev/null 2>&1
    /usr/bin/time -f "%e %M" -o "$work/t" "$edoctl" $plan "$work/$part-s.toml" \
        --report "$work/edo-s.json" --gcode "$work/edo-s.gcode" >/dev/null 2>&1
    edo_time=$(cat "$work/t")
    before=$("$check" "$work/edo.gcode" $nozzle 2>/dev/null | area)
    after=$("$check" "$work/edo-s.gcode" $nozzle 2>/dev/null | area)
    roads=$(python3 -c "import json; s=json.load(open('$work/edo-s.json'))['support']; print('%.0f %.0f' % (s['roads_mm'], s['road_volume_mm3']))")
    printf '| %s | edo | %s | %s | %s | %s | %s | %s |\n' "$part" "$before" "$after" \
        "${roads% *}" "${roads#* }" "${edo_time% *}" "$(( ${edo_time#* } / 1024 ))"

    ps="prusa-slicer --export-gcode --layer-height $layer --first-layer-height $layer \
        --nozzle-diameter $nozzle --perimeters 100 --fill-density 0 --top-solid-layers 0 \
        --bottom-solid-layers 0 --skirts 0 --bed-shape 0x0,300x0,300x300,0x300 \
        --max-print-height 500 --center 150,150"
    $ps --output "$work/ps.gcode" "$mesh" >/dev/null 2>&1
    /usr/bin/time -f "%e %M" -o "$work/t" $ps --support-material --support-material-auto \
        --support-material-threshold 60 --support-material-contact-distance 0 --output "$work/ps-s.gcode" "$mesh" >/dev/null 2>&1
    ps_time=$(cat "$work/t")
    python3 "$work/from_prusaslicer.py" "$work/ps.gcode" "$work/ps-r.gcode"
    python3 "$work/from_prusaslicer.py" "$work/ps-s.gcode" "$work/ps-s-r.gcode"
    before=$("$check" "$work/ps-r.gcode" $nozzle 2>/dev/null | area)
    after=$("$check" "$work/ps-s-r.gcode" $nozzle 2>/dev/null | area)
    roads=$(python3 "$work/prusaslicer_support.py" "$work/ps-s-r.gcode")
    printf '| %s | PrusaSlicer | %s | %s | %s | %s | %s | %s |\n' "$part" "$before" "$after" \
        "${roads% *}" "${roads#* }" "${ps_time% *}" "$(( ${ps_time#* } / 1024 ))"
done
