#!/usr/bin/python3
"""Packaging: installs the build into a temporary prefix, builds examples/consumer against it with
find_package(crowdmap), generates the Python stubs from the installed protos, and runs both
clients against the installed mapd (a small simulated map), checking what they print against
mapctl's GetMapInfo and QueryRegion.
Usage: packaging_test.py --build BUILD_DIR --source SOURCE_DIR"""
import argparse
import glob
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time


def run(args, **kwargs):
    result = subprocess.run(args, capture_output=True, text=True, **kwargs)
    if result.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} failed ({result.returncode}):\n{result.stdout}\n{result.stderr}")
    return result.stdout


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--build", required=True)
    parser.add_argument("--source", required=True)
    args = parser.parse_args()
    work = tempfile.mkdtemp(prefix="packaging-test-")
    prefix = os.path.join(work, "prefix")
    run(["cmake", "--install", args.build, "--prefix", prefix])
    for path in ("bin/mapd", "bin/mapctl", "bin/mapsim", "lib/libcrowdmap_client.a",
                 "lib/cmake/crowdmap/crowdmap-config.cmake", "lib/cmake/crowdmap/crowdmap-config-version.cmake",
                 "include/crowdmap/client/api/map_client.h", "include/crowdmap/mapservice/v1/map_service.grpc.pb.h",
                 "share/crowdmap/proto/mapservice/v1/map_service.proto"):
        if not os.path.exists(os.path.join(prefix, path)):
            raise RuntimeError(f"not installed: {path}")

    consumer = os.path.join(work, "consumer")
    run(["cmake", "-S", os.path.join(args.source, "examples/consumer"), "-B", consumer, "-G", "Ninja",
         f"-DCMAKE_PREFIX_PATH={prefix}", "-DCMAKE_BUILD_TYPE=Release"])
    run(["cmake", "--build", consumer])

    stubs = os.path.join(work, "py")
    os.makedirs(stubs)
    protos = os.path.join(prefix, "share/crowdmap/proto")
    run(["protoc", "-I", protos, f"--python_out={stubs}", f"--grpc_out={stubs}",
         "--plugin=protoc-gen-grpc=/usr/bin/grpc_python_plugin",
         *sorted(glob.glob(os.path.join(protos, "mapservice/v1/*.proto")))])

    log_path = os.path.join(work, "mapd.log")
    log = open(log_path, "w")
    mapd = subprocess.Popen([os.path.join(prefix, "bin/mapd"), "--db", os.path.join(work, "map.db"), "--create",
                             "--listen", "127.0.0.1:0"], stdout=log, stderr=subprocess.STDOUT)
    try:
        port = None
        deadline = time.time() + 30
        while port is None and time.time() < deadline and mapd.poll() is None:
            if m := re.search(r"event=started .*? port=(\d+)", open(log_path).read()):
                port = int(m.group(1))
            time.sleep(0.05)
        if port is None:
            raise RuntimeError("mapd did not start:\n" + open(log_path).read())
        server = f"127.0.0.1:{port}"
        run([os.path.join(prefix, "bin/mapsim"), "fleet", "--server", server, "--passages", "3", "--vehicles", "1",
             "--quiet", "--out", os.path.join(work, "fleet")])
        info = json.loads(run([os.path.join(prefix, "bin/mapctl"), "info", "--json", "--server", server]))
        region = json.loads(run([os.path.join(prefix, "bin/mapctl"), "region", "--bbox", "-180,-85,180,85",
                                 "--json", "--server", server]))
        expected_cpp = (f"server_version={info['server_version']} map_version={info['map_version']} "
                        f"landmarks={info['landmark_count']}")
        expected_py = (f"server_version={info['server_version']} map_version={info['map_version']} "
                       f"landmarks={len(region['landmarks'])}")
        got_cpp = run([os.path.join(consumer, "map_info"), server]).strip()
        env = dict(os.environ, PYTHONPATH=stubs)
        got_py = run(["/usr/bin/python3", os.path.join(args.source, "examples/python/map_info.py"), server],
                     env=env).strip()
        # The packed covariance example, on a box holding every landmark: its sigmas are the
        # marginals mapctl reads (printed to the millimetre).
        first = region["landmarks"][0]
        covariance_lines = run(["/usr/bin/python3", os.path.join(args.source, "examples/python/region_covariance.py"),
                                server, str(first["lat_deg"]), str(first["lon_deg"]), "20000"], env=env).splitlines()
    finally:
        mapd.send_signal(signal.SIGTERM)
        mapd.wait(timeout=30)
        log.close()
    failures = 0
    for name, got, expected in (("C++ consumer", got_cpp, expected_cpp), ("Python client", got_py, expected_py)):
        ok = got == expected and int(info["landmark_count"]) > 0
        failures += not ok
        print(("ok   " if ok else "FAIL ") + f"{name}: '{got}', mapctl: '{expected}'")
    sigma_east = {int(l["id"]): math.sqrt(l["cov_en_m2"]["ee"]) for l in region["landmarks"]}
    printed = {int(line.split()[0]): float(re.search(r"sigma_east_m=([0-9.]+)", line).group(1))
               for line in covariance_lines[1:]}
    ok = (covariance_lines[0].endswith(f"landmarks={len(sigma_east)}") and printed.keys() == sigma_east.keys()
          and all(abs(printed[i] - sigma_east[i]) <= 0.0015 for i in printed))
    failures += not ok
    print(("ok   " if ok else "FAIL ") + f"Python packed covariance: '{covariance_lines[0]}', "
          f"{len(printed)} landmarks' sigmas against mapctl's")
    if failures:
        print(f"work folder kept: {work}")
        return 1
    shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
