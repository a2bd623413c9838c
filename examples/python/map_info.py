#!/usr/bin/python3
"""Reads the map's version and the landmarks in a box from mapd: map_info.py [HOST:PORT]
Stubs (Debian: protobuf-compiler, protobuf-compiler-grpc, python3-grpcio), see the README:
  protoc -I proto --python_out=gen --grpc_out=gen --plugin=protoc-gen-grpc=/usr/bin/grpc_python_plugin \\
      proto/mapservice/v1/*.proto
  PYTHONPATH=gen examples/python/map_info.py 127.0.0.1:50051"""
import sys

import grpc
from mapservice.v1 import map_pb2, map_service_pb2, map_service_pb2_grpc

stub = map_service_pb2_grpc.MapServiceStub(grpc.insecure_channel(sys.argv[1] if len(sys.argv) > 1 else "127.0.0.1:50051"))
info = stub.GetMapInfo(map_service_pb2.GetMapInfoRequest(), timeout=10)
box = map_pb2.BoundingBox(min_lat_deg=-85, min_lon_deg=-180, max_lat_deg=85, max_lon_deg=180)
region = stub.QueryRegion(map_service_pb2.QueryRegionRequest(box=box, page_size=10000), timeout=10)
print(f"server_version={info.server_version} map_version={info.map_version} landmarks={len(region.landmarks)}")
