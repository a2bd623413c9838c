#!/usr/bin/env bash
# Installs what is missing, builds, and starts the map service on its embedded SQLite default
# (./var/map.db, created on first start, listening on 127.0.0.1:50051). Extra arguments go to
# mapd; see `build/server/mapd --help`.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
mkdir -p var
exec "${BUILD_DIR:-build}/server/mapd" "$@"
