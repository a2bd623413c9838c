#!/usr/bin/env bash
# A sweep of varied city fleets with the estimator's defaults (joint solves, gates): 32 runs of
# `mapsim city --passages 60`, routes of 400 and 1000 m, the four noise models, with and without
# per-vehicle camera errors (each vehicle's yaw estimated), sensor rates +-20% per vehicle, two
# seeds (noise and layout). Prints one line per run, then the passages refused (false refusals:
# every passage is clean) and the mean error, NEES and error over the Cramer-Rao bound per noise
# model.
#   scripts/city-sweep.sh [OUT_DIR]        (default out/city-sweep; JOBS=2 runs two at a time,
#                                           EXTRA_FLAGS="..." adds mapsim city flags to every run)
# About 15 minutes with JOBS=2 on a 2-core machine. Runs already in OUT_DIR are kept.
# SEEDS, NOISES, ROUTES and CAMERA_ERRORS (per-vehicle yaw sigmas, rad) replace the sweep's lists,
# e.g. a Monte Carlo of one configuration over many seeds:
#   SEEDS="$(seq 1 10)" NOISES=gnss-ar1 CAMERA_ERRORS=0 JOBS=2 scripts/city-sweep.sh out/ar1-mc
set -euo pipefail
cd "$(dirname "$0")/.."
OUT="${1:-out/city-sweep}"
MAPSIM="${MAPSIM:-build/client/mapsim}"
JOBS="${JOBS:-1}"
mkdir -p "$OUT"
for seed in ${SEEDS:-1 2}; do for noise in ${NOISES:-white gnss-ar1 yaw-bias ar1+yaw}; do
for route in ${ROUTES:-400 1000}; do for vy in ${CAMERA_ERRORS:-0 0.0087}; do
  echo "$noise-r$route-v$vy-s$seed $route $noise $vy $seed"
done; done; done; done | xargs -P "$JOBS" -L 1 bash -c '
  name=$0 route=$1 noise=$2 vy=$3 seed=$4
  if [ ! -f "'"$OUT"'/$name/summary.json" ]; then
    "'"$MAPSIM"'" city --passages 60 --route-m "$route" --noise "$noise" --vehicle-yaw-bias-sigma-rad "$vy" \
      --estimate-camera-yaw --rate-variation 0.2 --seed "$seed" --layout-seed "$seed" ${EXTRA_FLAGS:-} --out "'"$OUT"'/$name" \
      --quiet > "'"$OUT"'/$name.log" 2>&1
  fi
  echo "$name $(tail -n 1 "'"$OUT"'/$name.log" | grep -o "failed=[0-9]*\|quarantined=[0-9]*\| mean_error_m=[0-9.]*\| nees_per_dof=[0-9.]*\|error_over_crlb=[0-9.na]*" | tr "\n" " ")"'
/usr/bin/python3 - "$OUT" <<'PY'
import json, pathlib, sys
runs = [json.loads(p.read_text()) | {"name": p.parent.name} for p in sorted(pathlib.Path(sys.argv[1]).glob("*/summary.json"))]
passages = sum(r["passages"] for r in runs)
refused = sum(r["passages_failed"] for r in runs)
quarantined = sum(r["passages_quarantined"] for r in runs)
print(f"{len(runs)} runs, {passages} passages, {refused} refused ({100.0 * refused / max(passages, 1):.2f}%; {quarantined} of them quarantined)")
def line(label, sel):
    nees = [r["nees_per_dof"] for r in sel]
    bound = [r["error_over_crlb"] for r in sel if r.get("error_over_crlb") is not None]
    against_bound = (f", error / CRLB {sum(bound) / len(bound):.2f} (runs {min(bound):.2f} to {max(bound):.2f})"
                     if len(bound) == len(sel) else "")
    print(f"{label}: mean error {sum(r['mean_error_m'] for r in sel) / len(sel):.3f} m, "
          f"NEES/dof {sum(nees) / len(nees):.2f} (runs {min(nees):.2f} to {max(nees):.2f}){against_bound} over {len(sel)} runs")
for noise in ("white", "gnss-ar1", "yaw-bias", "ar1+yaw"):
    sel = [r for r in runs if r["name"].startswith(noise + "-r")]
    if sel:
        line(f"  {noise}", sel)
        for route in sorted({int(r["name"][len(noise) + 2:].split("-")[0]) for r in sel}):
            line(f"    {route} m routes", [r for r in sel if r["name"].startswith(f"{noise}-r{route}-")])
PY
