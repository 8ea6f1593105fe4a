#!/usr/bin/env bash
# The runs behind results/ (issue 5), two at a time with one thread each; rerun this script to
# continue: a run with a checkpoint is resumed (--resume), a finished one is skipped.
#   bash results/commands.sh [RUNS_DIR]     (default: runs/evidence)
#   JOBS=3 bash results/commands.sh RUNS_DIR   (three at a time: fewer idle cores when few runs are left)
# After (or during) the runs, copy their CSVs and flags into results/ and draw the figures:
#   for d in runs/evidence/*/; do n=results/runs/$(basename "$d"); mkdir -p "$n";
#     cp "$d/config.json" "$d/progress.csv" "$n/"; done; python plot.py
set -u
cd "$(dirname "$0")/.."
RUNS=${1:-runs/evidence}
STEPS=300000
JOBS=${JOBS:-2}
mkdir -p "$RUNS"

run() {  # run NAME SAIL.PY-FLAGS...
  local name=$1; shift
  local dir="$RUNS/$name"
  if [ -f "$dir/progress.csv" ] && [ ! -f "$dir/checkpoint.pt" ]; then
    return 0  # BC, finished (it trains from the demos only and keeps no checkpoint)
  elif [ -f "$dir/checkpoint.pt" ]; then
    python - "$dir" "$STEPS" <<'PY' && return 0  # finished: skip
import csv, sys
rows = list(csv.DictReader(open(sys.argv[1] + "/progress.csv")))
sys.exit(0 if rows and float(rows[-1]["global_step"]) >= int(sys.argv[2]) else 1)
PY
    python sail.py --resume "$dir" --total-timesteps "$STEPS" --threads 1 > "$dir.log" 2>&1
  elif [ "$1" = "--env" ] && [ "$3" = "--algo" ] && [ "$4" = "bc" ]; then  # BC: bc.py, no env steps
    rm -rf "$dir"
    python bc.py --env "$2" "${@:5}" --threads 1 --output-dir "$RUNS" --run-name "$name" > "$dir.log" 2>&1
  else
    rm -rf "$dir"
    python sail.py "$@" --total-timesteps "$STEPS" --threads 1 --checkpoint-freq 10000 \
      --output-dir "$RUNS" --run-name "$name" > "$dir.log" 2>&1
  fi
}
export -f run
export RUNS STEPS

# name, then the flags: the order is the priority
cat <<'LIST' | xargs -P "$JOBS" -L 1 bash -c 'run "$@"' _
Hopper-v5__sail__1 --env Hopper-v5 --algo sail --seed 1
Walker2d-v5__sail__1 --env Walker2d-v5 --algo sail --seed 1
Hopper-v5__sail__2 --env Hopper-v5 --algo sail --seed 2
Walker2d-v5__sail__2 --env Walker2d-v5 --algo sail --seed 2
Hopper-v5__sail__3 --env Hopper-v5 --algo sail --seed 3
Walker2d-v5__sail__3 --env Walker2d-v5 --algo sail --seed 3
Hopper-v5__bc__1 --env Hopper-v5 --algo bc --seed 1
Hopper-v5__bc__2 --env Hopper-v5 --algo bc --seed 2
Hopper-v5__bc__3 --env Hopper-v5 --algo bc --seed 3
Walker2d-v5__bc__1 --env Walker2d-v5 --algo bc --seed 1
Walker2d-v5__bc__2 --env Walker2d-v5 --algo bc --seed 2
Walker2d-v5__bc__3 --env Walker2d-v5 --algo bc --seed 3
Hopper-v5__no-adaptation__1 --env Hopper-v5 --algo sail --no-adaptation --seed 1
Walker2d-v5__no-adaptation__1 --env Walker2d-v5 --algo sail --no-adaptation --seed 1
HalfCheetah-v5__sail__1 --env HalfCheetah-v5 --algo sail --seed 1
Swimmer-v5__sail__1 --env Swimmer-v5 --algo sail --seed 1
Hopper-v5__dac__1 --env Hopper-v5 --algo dac --seed 1
Walker2d-v5__dac__1 --env Walker2d-v5 --algo dac --seed 1
Hopper-v5__td3__1 --env Hopper-v5 --algo td3 --seed 1
Walker2d-v5__td3__1 --env Walker2d-v5 --algo td3 --seed 1
HalfCheetah-v5__sail__2 --env HalfCheetah-v5 --algo sail --seed 2
Swimmer-v5__sail__2 --env Swimmer-v5 --algo sail --seed 2
Hopper-v5__no-lfd__1 --env Hopper-v5 --algo sail --no-lfd --seed 1
Hopper-v5__on-policy-disc__1 --env Hopper-v5 --algo sail --on-policy-disc --seed 1
Hopper-v5__no-adaptation__2 --env Hopper-v5 --algo sail --no-adaptation --seed 2
Walker2d-v5__no-adaptation__2 --env Walker2d-v5 --algo sail --no-adaptation --seed 2
Hopper-v5__fixed-alpha__1 --env Hopper-v5 --algo sail --fixed-alpha --seed 1
Hopper-v5__dac__2 --env Hopper-v5 --algo dac --seed 2
Walker2d-v5__dac__2 --env Walker2d-v5 --algo dac --seed 2
HalfCheetah-v5__dac__1 --env HalfCheetah-v5 --algo dac --seed 1
Swimmer-v5__dac__1 --env Swimmer-v5 --algo dac --seed 1
Hopper-v5__no-lfd__2 --env Hopper-v5 --algo sail --no-lfd --seed 2
Hopper-v5__on-policy-disc__2 --env Hopper-v5 --algo sail --on-policy-disc --seed 2
Hopper-v5__fixed-alpha__2 --env Hopper-v5 --algo sail --fixed-alpha --seed 2
Hopper-v5__no-lfd__3 --env Hopper-v5 --algo sail --no-lfd --seed 3
Hopper-v5__on-policy-disc__3 --env Hopper-v5 --algo sail --on-policy-disc --seed 3
Hopper-v5__fixed-alpha__3 --env Hopper-v5 --algo sail --fixed-alpha --seed 3
LIST
