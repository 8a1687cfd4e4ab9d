#!/bin/bash
# The numbers of docs/effects.md, "Measured at the tip" (image campaigns on the context plan).
# Usage: docs/examples/context_walkthrough.sh WORKDIR SEED...   (from the repository root, after make setup)
# Per seed: a clean campaign, a hidden 20 µm/h time-driven thermal drift on X, an 8 µm backlash on Z and
# the user family docs/examples/cross_backlash.py (8 µm along Y by X's approach), small images, the
# context plan (PLAN=small for the small one). Each hidden-effect campaign is diagnosed, then calibrated
# with the diagnosis' spec: the accepted one ("next: ..."), or, when nothing is accepted, its best
# candidate ("the best candidate, `SPEC`"); the user campaign is diagnosed without its module (what
# someone without the class gets), then calibrated with it, its amount fitted from zero.
# A step whose log has the calibration's tip errors is not run again. The last line prints
# docs/examples/context_summary.py's table.
set -u
W=$1; shift
C=$W/campaigns; R=$W/results; REP=$W/reports; L=$W/logs
mkdir -p "$C" "$L"
FC=".venv/bin/fivecal"
MODULE=docs/examples/cross_backlash.py
best() {
  local accepted; accepted=$(sed -n "s/^next: fivecal calibrate .* --add-effect '\(.*\)'$/\1/p" "$1")
  [ -n "$accepted" ] && echo "$accepted" || sed -n 's/^Nothing significant: the best candidate, `\([^`]*\)`.*/\1/p' "$1" | head -1
}
sim() { local out=$1; shift; [ -e "$C/$out/manifest.csv" ] || nice -n 10 $FC simulate "$C/$out" --size small --plan "${PLAN:-context}" "$@" > "$L/$out-simulate.log" 2>&1; }
run() { local log=$1; shift; grep -q '^mean tip errors' "$L/$log.log" 2>/dev/null && return; nice -n 10 /usr/bin/time -f "%e s" $FC "$@" --results "$R" --reports "$REP" > "$L/$log.log" 2>&1; }
ids=()
for seed in "$@"; do
  sim clean-s$seed --seed $seed
  sim drift-s$seed --seed $seed --effect thermal_drift:axis=X,driver=time,um_per_hour=20
  sim backlash-s$seed --seed $seed --effect backlash:axis=Z,amount_um=8
  sim user-s$seed --seed $seed --effect-module $MODULE --effect cross_backlash:axis=X,along=Y,amount_um=8
  run clean-s$seed-diagnose diagnose "$C/clean-s$seed"
  for name in drift backlash; do
    run $name-s$seed-diagnose diagnose "$C/$name-s$seed"
    spec=$(best "$L/$name-s$seed-diagnose.log")
    [ -n "$spec" ] && run $name-s$seed-add calibrate "$C/$name-s$seed" --add-effect "$spec"
  done
  run user-s$seed-diagnose diagnose "$C/user-s$seed"
  # the user wrote the class after reading what the residual follows: added with its amount fitted from 0
  run user-s$seed-add calibrate "$C/user-s$seed" --effect-module $MODULE \
    --add-effect cross_backlash:axis=X,along=Y,amount_um=0
  ids+=(clean-s$seed drift-s$seed backlash-s$seed user-s$seed)
done
.venv/bin/python docs/examples/context_summary.py "$R" "${ids[@]}"
