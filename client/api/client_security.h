#ifndef CROWDMAP_CLIENT_API_CLIENT_SECURITY_H_
#define CROWDMAP_CLIENT_API_CLIENT_SECURITY_H_

#include <memory>
#include <string>

#include <grpcpp/security/credentials.h>

#include "absl/status/statusor.h"

namespace crowdmap {

// How a client proves who it is and checks whom it talks to. All empty: plaintext, anonymous
// (what mapd accepts on loopback by default).
struct ClientSecurityOptions {
  std::string tls_ca;           // PEM file of the CA that signed mapd's certificate; set: TLS
  std::string tls_cert;         // PEM client certificate (mTLS), with tls_key
  std::string tls_key;
  std::string tls_server_name;  // the name mapd's certificate must carry, when not the address's host
  std::string token;            // bearer token, sent as "authorization: Bearer TOKEN" on every call

  absl::Status Validate() const;
};

// TLS credentials (reading the PEM files; errors name the flag), or insecure ones without tls_ca.
absl::StatusOr<std::shared_ptr<grpc::ChannelCredentials>> MakeChannelCredentials(const ClientSecurityOptions& options);

// Reads the bearer token from the file at `path` into `options->token` (whitespace around it
// ignored); errors name --token-file.
absl::Status ReadTokenFile(const std::string& path, ClientSecurityOptions* options);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_API_CLIENT_SECURITY_H_
