#!/bin/bash
# Times QueryRegion of 500 m boxes with their covariance on a copy of a map, idle and then while
# new passages are applied: scripts/query-region-bench.py's line (p50/p99/max ms) for each, and
# how many passages the worker applied during the second.
#
#   scripts/reads-under-writes-bench.sh MAP_DB PASSAGE_DIR [BOXES] [FORMAT]
#
# BOXES (default 300) random boxes each time; FORMAT packed (default) or blocks, the covariance
# layout asked for. MAP_DB is copied (with MAP_DB.queue) to a scratch directory and left untouched;
# PASSAGE_DIR holds passage files not yet applied to it (`mapsim city ... --export-passages DIR
# --export-format binary`). MAPD (default build/server/mapd) and MAPD_ARGS (default: 2 links for
# updates, 1 for reads, no warm-up or re-solves) pick the server. The reader needs Python stubs in
# GEN (default ./gen; see query-region-bench.py).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
# shellcheck source=lib/mapd-bench.sh
source "$ROOT/scripts/lib/mapd-bench.sh"
usage_unless "$0" "$@"
MAP_DB=$1
PASSAGES=$2
BOXES=${3:-300}
FORMAT=${4:-packed}
MAPD=${MAPD:-$ROOT/build/server/mapd}
MAPCTL=${MAPCTL:-$ROOT/build/client/mapctl}
MAPD_ARGS=${MAPD_ARGS:---window-hops 2 --read-window-hops 1 --warmup-passages 0 --relinearize-until-passages 0}
GEN=${GEN:-$ROOT/gen}
PORT=${PORT:-50392}
SCRATCH=$(mktemp -d /tmp/reads-under-writes.XXXXXX)
UPLOAD_PID=
trap 'stop_bench ${UPLOAD_PID:+"$UPLOAD_PID"}' EXIT
passage_files "$PASSAGES"
copy_map "$MAP_DB" "$SCRATCH"
# shellcheck disable=SC2086
start_mapd "$MAPD" "$SCRATCH/mapd.log" --db "$SCRATCH/map.db" --listen "127.0.0.1:$PORT" \
  --vehicle-upload-rate 1000 --vehicle-upload-burst 1000 $MAPD_ARGS
read_boxes() {
  PYTHONPATH=$GEN /usr/bin/python3 "$ROOT/scripts/query-region-bench.py" "127.0.0.1:$PORT" "$BOXES" "$FORMAT" | tail -1
}
echo "idle: $(read_boxes)"
"$MAPCTL" upload --server "127.0.0.1:$PORT" "${FILES[@]}" > "$SCRATCH/upload.log" 2>&1 &
UPLOAD_PID=$!
until (( $(finished_count "$SCRATCH/mapd.log") > 0 )); do sleep 0.2; done
BEFORE=$(finished_count "$SCRATCH/mapd.log")
LINE=$(read_boxes)
echo "while passages are applied: $LINE ($(( $(finished_count "$SCRATCH/mapd.log") - BEFORE )) applied during the reads)"
