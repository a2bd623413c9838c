#!/usr/bin/python3
"""Reads the landmarks of a box with their joint covariance (the packed layout) and prints each
landmark's sigmas and its strongest correlation with another landmark of the box:
  region_covariance.py HOST:PORT LAT LON [HALF_WIDTH_M]     (default half width 250 m)
Stubs as for map_info.py (see the README); numpy: Debian's python3-numpy.
  PYTHONPATH=gen examples/python/region_covariance.py 127.0.0.1:50051 48.70 2.17"""
import math
import sys

import grpc
import numpy as np
from mapservice.v1 import map_pb2, map_service_pb2, map_service_pb2_grpc


def packed_values(packed):
    """PackedCovariance.upper_m2 as a numpy array. np.array(packed.upper_m2) converts value by value
    (10-18 ms for a 500 m box of 260 landmarks here); the field's bytes are the little-endian doubles
    themselves, and protobuf writes fields in number order, so they end the message's serialization
    (under 1 ms). Checked on the first and last values, else the slow way."""
    count = len(packed.upper_m2)
    if count == 0:
        return np.zeros(0)
    raw = packed.SerializeToString()
    if len(raw) >= 8 * count:
        values = np.frombuffer(raw, dtype="<f8", offset=len(raw) - 8 * count)
        if values[0] == packed.upper_m2[0] and values[-1] == packed.upper_m2[count - 1]:
            return values
    return np.array(packed.upper_m2, dtype=float)


def covariance_matrix(packed):
    """The symmetric matrix of a PackedCovariance: its upper triangle row by row."""
    upper = packed_values(packed)
    rows, cols = np.triu_indices(packed.dim)  # row by row, as map.proto lays it out
    matrix = np.empty((packed.dim, packed.dim))
    matrix[rows, cols] = upper
    matrix[cols, rows] = upper
    return matrix


def main():
    if len(sys.argv) not in (4, 5):
        sys.exit(__doc__)
    lat, lon = float(sys.argv[2]), float(sys.argv[3])
    half_width_m = float(sys.argv[4]) if len(sys.argv) == 5 else 250.0
    dlat = half_width_m / 111320.0
    dlon = dlat / math.cos(math.radians(lat))
    stub = map_service_pb2_grpc.MapServiceStub(
        grpc.insecure_channel(sys.argv[1], options=[("grpc.max_receive_message_length", 256 << 20)]))
    box = map_pb2.BoundingBox(min_lat_deg=lat - dlat, max_lat_deg=lat + dlat, min_lon_deg=lon - dlon,
                              max_lon_deg=lon + dlon)
    # One page: the covariance is joint within a page only, so ask for all of the box at once.
    page = stub.QueryRegion(map_service_pb2.QueryRegionRequest(
        box=box, page_size=2000, include_cross_covariance=True,
        covariance_format=map_pb2.COVARIANCE_FORMAT_PACKED), timeout=60)
    if page.next_page_token:
        sys.exit("more than 2000 landmarks in the box: take a smaller one")
    n = len(page.landmarks)
    print(f"map_version={page.map_version} landmarks={n}")
    if n == 0:
        return
    cov = covariance_matrix(page.packed_covariance)
    sigma = np.sqrt(np.diag(cov))
    correlation = cov / np.outer(sigma, sigma)
    for i, landmark in enumerate(page.landmarks):
        # Strongest East or North correlation with another landmark of the box.
        others = np.abs(correlation[2 * i:2 * i + 2]).max(axis=0).reshape(n, 2).max(axis=1)
        others[i] = 0.0
        j = int(np.argmax(others)) if n > 1 else i
        print(f"{landmark.id} {landmark.lat_deg:.7f} {landmark.lon_deg:.7f} sigma_east_m={sigma[2 * i]:.3f} "
              f"sigma_north_m={sigma[2 * i + 1]:.3f} most_correlated={page.landmarks[j].id} ({others[j]:.2f})")


if __name__ == "__main__":
    main()
