#!/usr/bin/env bash
# Installs what is missing, builds, and runs the whole test suite (a few minutes on 2 cores).
#   scripts/test.sh                 all tests
#   scripts/test.sh -R core_        only tests whose name matches (ctest arguments pass through)
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
cd "${BUILD_DIR:-build}"
ctest --output-on-failure -j "$(nproc)" --timeout 600 "$@"
