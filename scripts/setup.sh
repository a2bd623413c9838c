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
  libsqlite3-dev sqlite3 libspdlog-dev libfmt-dev libssl-dev
  libgeographiclib-dev libabsl-dev prometheus-cpp-dev
  libcivetweb-dev libjs-leaflet
  python3 python3-yaml
  libssl-dev openssl
  libcli11-dev nlohmann-json3-dev
  # tcmalloc, the allocator of mapd, mapsim and the benchmarks (CMakeLists.txt: crowdmap_use_tcmalloc).
  libgoogle-perftools-dev
  # The BLAS and LAPACK behind CHOLMOD and the dense kernels: OpenBLAS's pthread build, selected
  # below. The service calls them from several threads at once (the worker beside the readers);
  # Debian's single-threaded OpenBLAS then returns wrong results (mapd refuses to start on it), and
  # ATLAS, safe, takes 1.4 to 1.9 times as long (docs/results.md, "OpenBLAS's pthread build").
  libopenblas0-pthread
)
# Only for the tests: GoogleTest, Google Benchmark, the map viewer's browser test (headless
# chromium through chromedriver and selenium) and the Python client examples' gRPC runtime and numpy.
TEST_PACKAGES=(
  libgtest-dev libgmock-dev libbenchmark-dev
  chromium chromium-driver python3-selenium
  python3-grpcio python3-protobuf python3-numpy
)
if ((TESTS)); then PACKAGES+=("${TEST_PACKAGES[@]}"); fi

missing=()
for p in "${PACKAGES[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed'; then
    missing+=("$p")
  fi
done

SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi

if ((${#missing[@]})); then
  echo "setup: installing ${#missing[@]} missing package(s): ${missing[*]}"
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
else
  echo "setup: all packages present"
fi

# libblas.so.3 and liblapack.so.3 from OpenBLAS's pthread build, also where another BLAS package
# (ATLAS, which Ceres pulls in; a single-threaded OpenBLAS) would take the alternatives over: see
# the packages above.
multiarch="$(gcc -print-multiarch)"
for lib in libblas.so.3 liblapack.so.3; do
  name="$lib-$multiarch"
  chosen="/usr/lib/$multiarch/openblas-pthread/$lib"
  if [ "$(readlink -f "/etc/alternatives/$name")" != "$(readlink -f "$chosen")" ]; then
    echo "setup: selecting OpenBLAS (pthread) for $lib"
    $SUDO update-alternatives --quiet --set "$name" "$chosen"
  fi
done

if ((!BUILD)); then exit 0; fi

BUILD_DIR="${BUILD_DIR:-build}"
BUILD_TYPE="${BUILD_TYPE:-Release}"
if [ ! -f "$BUILD_DIR/build.ninja" ]; then
  tests_flag=ON
  if ((!TESTS)); then tests_flag=OFF; fi
  cmake -S . -B "$BUILD_DIR" -G Ninja -DCMAKE_BUILD_TYPE="$BUILD_TYPE" -DCROWDMAP_BUILD_TESTS="$tests_flag"
fi
cmake --build "$BUILD_DIR" -j "$(nproc)"
