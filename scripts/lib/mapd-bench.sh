# Shared by the benches that apply passages through a real mapd on loopback (source it).
#   usage_unless SCRIPT ARGS...  with fewer than two ARGS or -h/--help first: SCRIPT's header
#                             comment (from line 2 to the first line that is not a comment), exit 2
#   passage_files DIR         FILES (DIR's passage-* files) and N, or exits when there are none
#   copy_map MAP_DB DIR       MAP_DB (and MAP_DB.queue) copied to DIR/map.db and synced, the original untouched
#   start_mapd MAPD LOG ARGS  mapd started in the background on ARGS, its log in LOG; returns once it
#                             listens (MAPD_PID), or exits with its log when it stops first
#   finished_count LOG        passages that reached a final state (applied, rejected, failed, quarantined)
#   wait_finished LOG N       waits until N passages are final, the count on stderr as it goes
#   stop_bench PIDS...        for an EXIT trap: kills PIDS, stops MAPD_PID and waits for it, removes
#                             SCRATCH unless KEEP is set

usage_unless() {
  local script=$1
  shift
  if [[ $# -lt 2 || "$1" == -h || "$1" == --help ]]; then
    sed -n '2,/^[^#]/p' "$script" | sed '$d' | sed 's/^# \{0,1\}//'
    exit 2
  fi
}

passage_files() {
  FILES=("$1"/passage-*)
  N=${#FILES[@]}
  [[ -e "${FILES[0]}" ]] || { echo "no passage files in $1" >&2; exit 1; }
}

copy_map() {
  cp "$1" "$2/map.db"
  if [[ -f "$1.queue" ]]; then cp "$1.queue" "$2/map.db.queue"; fi
  # The copies' hundreds of MB of dirty pages would otherwise be written back during the measured
  # run, into its first commits' fsyncs.
  sync
}

start_mapd() {
  local mapd=$1 log=$2
  shift 2
  "$mapd" "$@" > "$log" 2>&1 &
  MAPD_PID=$!
  until grep -q "event=started" "$log"; do
    kill -0 "$MAPD_PID" 2>/dev/null || { cat "$log" >&2; exit 1; }
    sleep 0.2
  done
}

finished_count() {
  grep -c -E "event=(applied|rejected|failed|quarantined) " "$1" || true
}

wait_finished() {
  local log=$1 n=$2
  while (( $(finished_count "$log") < n )); do
    sleep 0.2
    echo -ne "\rfinished $(finished_count "$log")/$n" >&2
  done
  echo >&2
}

stop_bench() {
  # `|| true`: a command that fails last in a list would end the trap (set -e) before the rest ran.
  if [[ $# -gt 0 ]]; then kill "$@" 2>/dev/null || true; fi
  if [[ -n "${MAPD_PID:-}" ]]; then kill "$MAPD_PID" 2>/dev/null && wait "$MAPD_PID" 2>/dev/null || true; fi
  if [[ -z "${KEEP:-}" ]]; then rm -rf "$SCRATCH"; fi
}
