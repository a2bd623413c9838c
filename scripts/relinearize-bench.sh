#!/bin/bash
# Applies the same passages to copies of one map with mapd --relinearize-sigmas X for each X given:
# prints the time the backlog took (first upload to last passage final), then the time the
# re-linearisations it earned took once the queue was empty (until GetMapInfo owes none), how many
# were committed and refused, their time each (p50 / p95) and mapd's peak resident memory.
#
#   scripts/relinearize-bench.sh MAP_DB PASSAGE_DIR [X...]     (default: 0 6)
#
# MAP_DB is copied (with MAP_DB.queue) to a scratch directory for each run and left untouched.
# PASSAGE_DIR holds passage files not yet applied to it (e.g. `mapsim city ... --seed 2
# --export-passages DIR --export-format binary`). mapd gets MAPD_ARGS too (default: the city
# settings below, which must be the map's). Needs a build (scripts/setup.sh); load stays on loopback.
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
# shellcheck source=lib/mapd-bench.sh
source "$ROOT/scripts/lib/mapd-bench.sh"
usage_unless "$0" "$@"
MAP_DB=$1
PASSAGES=$2
shift 2
SIGMAS=("${@:-0}")
[[ $# -eq 0 ]] && SIGMAS=(0 6)
BUILD=${BUILD:-$ROOT/build}
MAPD_ARGS=${MAPD_ARGS:---window-hops 2 --warmup-passages 0 --relinearize-until-passages 0}
PORT=${PORT:-50293}
SCRATCH=$(mktemp -d /tmp/relinearize-bench.XXXXXX)
[[ -n "${KEEP:-}" ]] || trap 'rm -rf "$SCRATCH"' EXIT
passage_files "$PASSAGES"

owed() {
  "$BUILD/client/mapctl" info --server "127.0.0.1:$PORT" --json |
    sed -n 's/.*"relinearizations_due": "\{0,1\}\([0-9]*\)"\{0,1\}.*/\1/p'
}

for X in "${SIGMAS[@]}"; do
  DIR=$SCRATCH/x$X
  mkdir -p "$DIR"
  copy_map "$MAP_DB" "$DIR"
  # shellcheck disable=SC2086
  start_mapd "$BUILD/server/mapd" "$DIR/mapd.log" --db "$DIR/map.db" --listen "127.0.0.1:$PORT" \
    --relinearize-sigmas "$X" $MAPD_ARGS
  PID=$MAPD_PID
  START=$(date +%s.%N)
  "$BUILD/client/mapctl" upload --server "127.0.0.1:$PORT" "${FILES[@]}" > "$DIR/upload.log"
  wait_finished "$DIR/mapd.log" "$N"
  APPLIED_AT=$(date +%s.%N)
  until [[ "$(owed)" == "0" || -z "$(owed)" ]]; do sleep 0.5; done
  IDLE_AT=$(date +%s.%N)
  HWM=$(awk '/VmHWM/ {print $2}' /proc/$PID/status)
  kill -INT $PID
  wait $PID || true
  COMMITTED=$(grep -c "event=relinearized " "$DIR/mapd.log" || true)
  REFUSED=$(grep -c "event=relinearization_failed" "$DIR/mapd.log" || true)
  EACH=$(awk '/event=relinearized / {for (i = 1; i <= NF; ++i) if ($i ~ /^total_ms=/) print substr($i, 10)}' \
      "$DIR/mapd.log" | sort -n |
    awk '{a[NR] = $1} END {if (NR) printf "%.0f/%.0f", a[int(NR * 0.5) + 1], a[int(NR * 0.95) + 1]; else printf "-"}')
  printf 'relinearize_sigmas=%s passages=%d backlog_s=%.1f relinearizing_s=%.1f committed=%d refused=%d each_ms_p50/p95=%s peak_rss_mb=%d\n' \
    "$X" "$N" "$(awk -v a="$START" -v b="$APPLIED_AT" 'BEGIN {print b - a}')" \
    "$(awk -v a="$APPLIED_AT" -v b="$IDLE_AT" 'BEGIN {print b - a}')" "$COMMITTED" "$REFUSED" "$EACH" $((HWM / 1024))
done
