#!/bin/bash
# compare_outputs.sh BIN_DIR REPO OUT: writes the plan reports, G-code (rrf, marlin,
# marlin direct mixing), layer SVGs and the demo's output of the example jobs in
# config/examples into OUT, with timings and paths scrubbed, so that two builds can be
# compared for byte-identical output after a refactor:
#   tests/compare_outputs.sh OLD/target/release OLD /tmp/a
#   tests/compare_outputs.sh target/release . /tmp/b
#   diff -r /tmp/a /tmp/b   # only the OUT paths in *.stdout and the record's t_s may differ
# (sed -E 's/"t_s":[0-9.]+,//' on out/demo/record.jsonl removes the timestamps.)
set -u
BIN=$(realpath "$1"); REPO=$2; mkdir -p "$3"; OUT=$(realpath "$3"); cd "$REPO"
for j in config/examples/*.toml; do n=$(basename $j .toml); BV=""; [ $n = femur-graded ] && BV="--build-volume 200,200,500"
  $BIN/edoctl plan $j $BV --quiet --report $OUT/$n.report.json --gcode $OUT/$n.rrf.gcode --svg $OUT/$n.svg --layers 0..3 > $OUT/$n.stdout 2>&1; echo "rc=$?" >> $OUT/$n.stdout
  $BIN/edoctl plan $j $BV --quiet --gcode $OUT/$n.marlin.gcode --flavor marlin >/dev/null 2>&1
  $BIN/edoctl plan $j $BV --quiet --gcode $OUT/$n.marlind.gcode --flavor marlin --marlin-direct-mixing >/dev/null 2>&1
done
(cd $OUT && timeout 600 $BIN/edoctl demo > demo.stdout 2>&1; echo "rc=$?" >> demo.stdout)
# scrub timings, paths and elapsed fields
sed -i -E 's/[0-9]+(\.[0-9]+)? ?(ms|s|µs)\b/T/g; s#/tmp/[^ "]*#TMP#g' $OUT/*.stdout
for f in $OUT/*.json; do python3 - "$f" <<'PY'
import json,sys
p=sys.argv[1]; d=json.load(open(p))
def scrub(x):
    if isinstance(x,dict): return {k:("T" if any(s in k for s in ("time","elapsed","_s","ms","duration","version","path")) else scrub(v)) for k,v in x.items()}
    if isinstance(x,list): return [scrub(v) for v in x]
    return x
json.dump(scrub(d),open(p,"w"),indent=1,sort_keys=True)
PY
done
