// Prints what GetMapInfo reports: map_info [HOST:PORT]
#include <iostream>

#include "client/api/map_client.h"

int main(int argc, char** argv) {
  crowdmap::MapClientOptions options;
  if (argc > 1) options.server = argv[1];
  auto client = crowdmap::MapClient::Create(options);
  if (!client.ok()) {
    std::cerr << client.status().ToString() << "\n";
    return 1;
  }
  auto info = (*client)->GetMapInfo();
  if (!info.ok()) {
    std::cerr << info.status().ToString() << "\n";
    return 1;
  }
  std::cout << "server_version=" << info->server_version() << " map_version=" << info->map_version()
            << " landmarks=" << info->landmark_count() << "\n";
  return 0;
}
