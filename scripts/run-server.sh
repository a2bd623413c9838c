#!/usr/bin/env bash
# Installs what is missing, builds, and starts the map service on its embedded SQLite default
# (./var/map.db, created on first start with --create, listening on 127.0.0.1:50051), with the
# map viewer on http://127.0.0.1:8080/. Extra arguments go to mapd and win over these (e.g.
# --http-listen 127.0.0.1:8081); see `build/server/mapd --help`.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
mkdir -p var
# mapd creates a map only when told to: here, the default map on the first start.
create=()
if [ ! -s var/map.db ]; then create=(--create); fi
exec "${BUILD_DIR:-build}/server/mapd" "${create[@]}" --http-listen 127.0.0.1:8080 "$@"
