#!/bin/bash
# Applies the same passages to copies of one map with mapd --workers 1, 2, ...: prints, for each,
# the passages applied per second (first upload to last passage finished), how many updates were
# computed again because another worker's commit touched what they read, and mapd's peak
# resident memory; then each count's speed-up over the first.
#
#   scripts/workers-bench.sh MAP_DB PASSAGE_DIR [WORKERS...]     (default: 1 2)
#
# MAP_DB is copied (with MAP_DB.queue) to a scratch directory for each run and left untouched.
# PASSAGE_DIR holds passage files not yet applied to it (e.g. `mapsim city ... --seed 2
# --export-passages DIR --export-format binary`). mapd gets MAPD_ARGS (default: the city settings
# below, which must be the map's, and no re-linearisation: the workers would start it on the queue's
# last passages, which the figures before it did not have). Needs a build (scripts/setup.sh); load
# stays on loopback.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
# shellcheck source=lib/mapd-bench.sh
source "$ROOT/scripts/lib/mapd-bench.sh"
usage_unless "$0" "$@"
MAP_DB=$1
PASSAGES=$2
shift 2
WORKERS=("${@:-1}")
[[ $# -eq 0 ]] && WORKERS=(1 2)
BUILD=${BUILD:-$ROOT/build}
MAPD_ARGS=${MAPD_ARGS:---window-hops 2 --warmup-passages 0 --relinearize-until-passages 0 --relinearize-sigmas 0}
PORT=${PORT:-50291}
SCRATCH=$(mktemp -d /tmp/workers-bench.XXXXXX)
[[ -n "${KEEP:-}" ]] || trap 'rm -rf "$SCRATCH"' EXIT
passage_files "$PASSAGES"

declare -A RATE
for W in "${WORKERS[@]}"; do
  DIR=$SCRATCH/w$W
  mkdir -p "$DIR"
  copy_map "$MAP_DB" "$DIR"
  # shellcheck disable=SC2086
  start_mapd "$BUILD/server/mapd" "$DIR/mapd.log" --db "$DIR/map.db" --listen "127.0.0.1:$PORT" --workers "$W" $MAPD_ARGS
  PID=$MAPD_PID
  START=$(date +%s.%N)
  "$BUILD/client/mapctl" upload --server "127.0.0.1:$PORT" "${FILES[@]}" > "$DIR/upload.log"
  wait_finished "$DIR/mapd.log" "$N"
  END=$(date +%s.%N)
  HWM=$(awk '/VmHWM/ {print $2}' /proc/$PID/status)
  kill -INT $PID
  wait $PID || true
  APPLIED=$(grep -c "event=applied " "$DIR/mapd.log")
  RECOMPUTED=$(grep -o "recomputed=[0-9]*" "$DIR/mapd.log" | awk -F= '{s += $2} END {print s + 0}')
  SECONDS_TAKEN=$(awk -v a="$START" -v b="$END" 'BEGIN {print b - a}')
  RATE[$W]=$(awk -v n="$N" -v s="$SECONDS_TAKEN" 'BEGIN {print n / s}')
  printf 'workers=%d passages=%d applied=%d seconds=%.1f passages_per_s=%.3f recomputed=%d peak_rss_mb=%d\n' \
    "$W" "$N" "$APPLIED" "$SECONDS_TAKEN" "${RATE[$W]}" "$RECOMPUTED" $((HWM / 1024))
done
FIRST=${WORKERS[0]}
for W in "${WORKERS[@]:1}"; do
  printf 'speedup workers=%d over workers=%d: %.2fx\n' "$W" "$FIRST" "$(awk -v a="${RATE[$W]}" -v b="${RATE[$FIRST]}" 'BEGIN {print a / b}')"
done
