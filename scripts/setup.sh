#!/usr/bin/env bash
# One-time set-up on Debian 12: installs the packages the project needs (only those missing)
# and configures + builds the project in ./build. Safe to run repeatedly.
#   scripts/setup.sh                 install what is missing, then build
#   scripts/setup.sh --no-build      install only
#   scripts/setup.sh --server-only   without what only the tests need (GoogleTest, Google
#                                    Benchmark, the browser of the viewer test); builds with
#                                    -DCROWDMAP_BUILD_TESTS=OFF
set -euo pipefail

cd "$(dirname "$0")/.."

BUILD=1
TESTS=1
for arg in "$@"; do
  case "$arg" in
    --no-build) BUILD=0 ;;
    --server-only) TESTS=0 ;;
    *) echo "setup: unknown argument $arg" >&2; exit 2 ;;
  esac
done

PACKAGES=(
  build-essential cmake ninja-build pkg-config git
  libceres-dev libsuitesparse-dev libeigen3-dev libgoogle-glog-dev libgflags-dev
  libgrpc++-dev libprotobuf-dev protobuf-compiler protobuf-compiler-grpc
  libsqlite3-dev sqlite3 libspdlog-dev libfmt-dev
  libgeographiclib-dev libabsl-dev prometheus-cpp-dev
  libcivetweb-dev libjs-leaflet
  python3 python3-yaml
  libssl-dev openssl
  libcli11-dev nlohmann-json3-dev
  # The BLAS and LAPACK behind CHOLMOD (libblas.so.3 and liblapack.so.3 alternatives): OpenBLAS,
  # single-threaded, instead of the generic ATLAS that Ceres pulls in (city passage 175 -> 154 ms,
  # docs/results.md "BLAS").
  libopenblas0-serial
)
# Only for the tests: GoogleTest, Google Benchmark, the map viewer's browser test (headless
# chromium through chromedriver and selenium) and the Python client example's gRPC runtime.
TEST_PACKAGES=(
  libgtest-dev libgmock-dev libbenchmark-dev
  chromium chromium-driver python3-selenium
  python3-grpcio python3-protobuf
)
if ((TESTS)); then PACKAGES+=("${TEST_PACKAGES[@]}"); fi

missing=()
for p in "${PACKAGES[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed'; then
    missing+=("$p")
  fi
done

if ((${#missing[@]})); then
  echo "setup: installing ${#missing[@]} missing package(s): ${missing[*]}"
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
else
  echo "setup: all packages present"
fi

if ((!BUILD)); then exit 0; fi

BUILD_DIR="${BUILD_DIR:-build}"
BUILD_TYPE="${BUILD_TYPE:-Release}"
if [ ! -f "$BUILD_DIR/build.ninja" ]; then
  tests_flag=ON
  if ((!TESTS)); then tests_flag=OFF; fi
  cmake -S . -B "$BUILD_DIR" -G Ninja -DCMAKE_BUILD_TYPE="$BUILD_TYPE" -DCROWDMAP_BUILD_TESTS="$tests_flag"
fi
cmake --build "$BUILD_DIR" -j "$(nproc)"
