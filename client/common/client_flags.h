#ifndef CROWDMAP_CLIENT_COMMON_CLIENT_FLAGS_H_
#define CROWDMAP_CLIENT_COMMON_CLIENT_FLAGS_H_

#include <string>

#include <CLI/CLI.hpp>

#include "absl/status/statusor.h"
#include "client/api/client_security.h"

// The flags of the tools that call mapd (mapctl; mapsim fleet and bench).
namespace crowdmap {

// --server HOST:PORT, the mapd address: default $MAPCTL_SERVER, else `*server` as it is.
CLI::Option* AddServerFlag(CLI::App* command, std::string* server);

// The client security flags as given; the token file is read by ClientSecurityFromFlags.
struct ClientSecurityFlags {
  ClientSecurityOptions options;  // without the token
  std::string token_file;
};

// --tls-ca, --tls-cert, --tls-key, --tls-server-name and --token-file (default
// $CROWDMAP_TOKEN_FILE): the token never comes from the command line itself.
void AddClientSecurityFlags(CLI::App* command, ClientSecurityFlags* flags);
// The options with the token read from the token file, validated; errors are usage errors.
absl::StatusOr<ClientSecurityOptions> ClientSecurityFromFlags(const ClientSecurityFlags& flags);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_COMMON_CLIENT_FLAGS_H_
