#!/usr/bin/python3
"""Times QueryRegion of 500 m boxes with cross-covariances against a running mapd: N boxes centred
on random landmarks of its map, one call each (the time until the response is decoded); prints the
landmarks per box, p50/p99/max ms and which call was the slowest. FORMAT is the covariance layout
asked for: packed (the default; one PackedCovariance) or blocks (a CrossCovariance per pair, which
this interpreter takes about 16 ms to decode for 250 landmarks).

  protoc -I proto --python_out=gen --grpc_out=gen --plugin=protoc-gen-grpc=/usr/bin/grpc_python_plugin \\
      proto/mapservice/v1/*.proto
  PYTHONPATH=gen scripts/query-region-bench.py 127.0.0.1:50051 100 [packed|blocks]

Debian: protobuf-compiler, protobuf-compiler-grpc, python3-grpcio (run with /usr/bin/python3)."""
import math
import random
import sys
import time

import grpc
from mapservice.v1 import map_pb2, map_service_pb2, map_service_pb2_grpc

HALF_WIDTH_M = 250.0
FORMATS = {"packed": map_pb2.COVARIANCE_FORMAT_PACKED, "blocks": map_pb2.COVARIANCE_FORMAT_BLOCKS}


def main():
    if len(sys.argv) not in (3, 4) or (len(sys.argv) == 4 and sys.argv[3] not in FORMATS):
        sys.exit(__doc__)
    server, boxes = sys.argv[1], int(sys.argv[2])
    layout = sys.argv[3] if len(sys.argv) == 4 else "packed"
    channel = grpc.insecure_channel(server, options=[("grpc.max_receive_message_length", 256 << 20)])
    stub = map_service_pb2_grpc.MapServiceStub(channel)
    world = map_pb2.BoundingBox(min_lat_deg=-85, min_lon_deg=-180, max_lat_deg=85, max_lon_deg=180)
    points, token = [], ""
    while True:
        page = stub.QueryRegion(map_service_pb2.QueryRegionRequest(box=world, page_size=10000, page_token=token),
                                timeout=60)
        points += [(l.lat_deg, l.lon_deg) for l in page.landmarks]
        token = page.next_page_token
        if not token:
            break
    if not points:
        sys.exit("the map is empty")
    random.seed(1)
    ms, sizes = [], []
    for _ in range(boxes):
        lat, lon = random.choice(points)
        dlat = HALF_WIDTH_M / 111320.0
        dlon = dlat / math.cos(math.radians(lat))
        box = map_pb2.BoundingBox(min_lat_deg=lat - dlat, max_lat_deg=lat + dlat, min_lon_deg=lon - dlon,
                                  max_lon_deg=lon + dlon)
        start = time.perf_counter()
        page = stub.QueryRegion(
            map_service_pb2.QueryRegionRequest(box=box, page_size=2000, include_cross_covariance=True,
                                               covariance_format=FORMATS[layout]), timeout=60)
        ms.append(1000.0 * (time.perf_counter() - start))
        sizes.append(len(page.landmarks))
    slowest = max(range(boxes), key=lambda i: ms[i])
    slowest_box = f"call {slowest + 1}, {sizes[slowest]} landmarks"
    ms.sort()
    sizes.sort()
    print(f"format={layout} landmarks_in_map={len(points)} boxes={boxes} landmarks_per_box_p50={sizes[boxes // 2]} "
          f"p50_ms={ms[boxes // 2]:.1f} p99_ms={ms[min(boxes - 1, int(0.99 * boxes))]:.1f} max_ms={ms[-1]:.1f} "
          f"(slowest: {slowest_box}; largest box {sizes[-1]} landmarks)")


if __name__ == "__main__":
    main()
