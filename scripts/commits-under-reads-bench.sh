#!/bin/bash
# Applies passages to a copy of a map while READERS clients read 500 m boxes with their
# cross-covariances back to back (scripts/query-region-bench.py, random boxes): prints the time
# from the first upload to the last passage applied and the p50/p95/max of the worker's commit
# time (mapd's commit_ms: the durable write and the publication, which waits for the map's lock
# that covariance reads hold).
#
#   scripts/commits-under-reads-bench.sh MAP_DB PASSAGE_DIR [READERS]     (default: 2 readers)
#
# MAP_DB is copied (with MAP_DB.queue) to a scratch directory and left untouched; PASSAGE_DIR holds
# passage files not yet applied to it (`mapsim city ... --export-passages DIR --export-format
# binary`). MAPD (default build/server/mapd) and MAPD_ARGS (default: no warm-up or re-solves) pick
# the server. The readers need Python stubs in GEN (default ./gen; see query-region-bench.py).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
# shellcheck source=lib/mapd-bench.sh
source "$ROOT/scripts/lib/mapd-bench.sh"
usage_unless "$0" "$@"
MAP_DB=$1
PASSAGES=$2
READERS=${3:-2}
MAPD=${MAPD:-$ROOT/build/server/mapd}
MAPCTL=${MAPCTL:-$ROOT/build/client/mapctl}
MAPD_ARGS=${MAPD_ARGS:---warmup-passages 0 --relinearize-until-passages 0}
GEN=${GEN:-$ROOT/gen}
PORT=${PORT:-50391}
SCRATCH=$(mktemp -d /tmp/commits-under-reads.XXXXXX)
READER_PIDS=()
trap 'stop_bench "${READER_PIDS[@]}"' EXIT
passage_files "$PASSAGES"
copy_map "$MAP_DB" "$SCRATCH"
# shellcheck disable=SC2086
start_mapd "$MAPD" "$SCRATCH/mapd.log" --db "$SCRATCH/map.db" --listen "127.0.0.1:$PORT" \
  --vehicle-upload-rate 1000 --vehicle-upload-burst 1000 $MAPD_ARGS
for r in $(seq "$READERS"); do
  PYTHONPATH=$GEN /usr/bin/python3 "$ROOT/scripts/query-region-bench.py" "127.0.0.1:$PORT" 1000000 \
    > "$SCRATCH/reader$r.txt" 2>&1 &
  READER_PIDS+=($!)
done
sleep 3  # the readers list the map's landmarks first
START=$(date +%s.%N)
"$MAPCTL" upload --server "127.0.0.1:$PORT" "${FILES[@]}" > "$SCRATCH/upload.log" 2>&1
wait_finished "$SCRATCH/mapd.log" "$N"
END=$(date +%s.%N)
/usr/bin/python3 - "$SCRATCH/mapd.log" "$START" "$END" "$READERS" <<'PY'
import re, sys
log, start, end, readers = sys.argv[1], float(sys.argv[2]), float(sys.argv[3]), sys.argv[4]
c = sorted(float(m) for m in re.findall(r"event=applied .*?commit_ms=([0-9.]+)", open(log).read()))
q = lambda p: c[min(len(c) - 1, int(p * len(c)))]
refused = len(re.findall(r"event=(?:rejected|failed|quarantined) ", open(log).read()))
print(f"readers={readers} applied={len(c)} refused={refused} seconds={end - start:.1f} commit_ms_p50={q(0.5):.1f} "
      f"commit_ms_p95={q(0.95):.1f} commit_ms_max={c[-1]:.1f}")
PY
