#ifndef CROWDMAP_SERVER_AUTH_H_
#define CROWDMAP_SERVER_AUTH_H_

#include <map>
#include <memory>
#include <mutex>
#include <shared_mutex>
#include <string>
#include <string_view>

#include <grpcpp/security/server_credentials.h>
#include <grpcpp/server_context.h>

#include "absl/status/statusor.h"
#include "server/request_log.h"

namespace crowdmap {

// TLS, authentication and the roles of mapd's clients.
struct SecurityOptions {
  std::string tls_cert;       // PEM certificate chain; with tls_key, mapd serves TLS only
  std::string tls_key;        // PEM private key
  std::string tls_client_ca;  // PEM CA bundle: client certificates are verified against it (mTLS)
  // "auto" (default): on unless mapd listens on loopback only (127.0.0.0/8, ::1, localhost, unix:).
  std::string auth = "auto";
  std::string auth_file;  // identities: token hashes and certificate names with their roles
  // "auto" (default): server reflection on exactly when authentication is off.
  std::string reflection = "auto";

  absl::Status Validate() const;
  bool tls() const { return !tls_cert.empty(); }
};

// True when `listen` (host:port or unix:path) accepts connections from this machine only.
bool IsLoopbackListen(const std::string& listen);
// Authentication resolved against the listen address ("auto").
bool AuthEnabled(const SecurityOptions& options, const std::string& listen);
bool ReflectionEnabled(const SecurityOptions& options, const std::string& listen);

// TLS (and mTLS with tls_client_ca) credentials, or insecure ones without tls_cert. Errors name
// the flag whose file cannot be read.
absl::StatusOr<std::shared_ptr<grpc::ServerCredentials>> MakeServerCredentials(const SecurityOptions& options);

// vehicle < operator < admin: each role may do what the ones below it may.
enum class Role { kVehicle = 0, kOperator = 1, kAdmin = 2 };
const char* RoleName(Role role);

// What an RPC needs.
enum class Permission {
  kReadMap,         // GetTile, QueryRegion, WatchRegion, GetMapInfo, GetLandmark, LocalizePassage
  kUpload,          // uploads: a vehicle as its own vehicle_id only, an admin as any
  kReadPassages,    // GetPassage, ListPassages, GetVehicle, ListVehicles: a vehicle its own only
  kAdministrate,    // ExcludePassage, ResolvePassage
};

// Who is calling. With authentication off every caller is `anonymous`, an admin.
struct Principal {
  std::string name;  // for a vehicle: its vehicle_id
  Role role = Role::kAdmin;
  std::string via = "none";  // token | x509 | none

  // OK when this principal may act for (upload as, read the passages of) `vehicle_id`.
  absl::Status MayActFor(const std::string& vehicle_id) const;
  bool MayReadAllPassages() const { return role >= Role::kOperator; }
  // The name its streams are counted under per identity: empty when authentication is off (every
  // caller is then `anonymous`, and not told apart).
  std::string stream_identity() const { return via == "none" ? std::string() : name; }
};

// Hex SHA-256 of `text` (OpenSSL libcrypto): how tokens are stored in the auth file.
std::string Sha256Hex(const std::string& text);

// The identities of an auth file, one per line ('#' starts a comment):
//   sha256:HEX ROLE NAME   a bearer token whose SHA-256 is HEX (`printf %s TOKEN | sha256sum`)
//   x509:CN ROLE NAME      a client certificate (verified against --tls-client-ca) with subject CN;
//                          x509:* ROLE * gives every other verified certificate ROLE, named by its CN
// ROLE is vehicle, operator or admin; a vehicle's NAME is the vehicle_id it uploads as.
// Reloaded on SIGHUP (Reload); a file that fails to parse leaves the loaded identities in place.
class Authenticator {
 public:
  // `auth_file` may be empty: then only x509:* style defaults are unavailable and nobody is known.
  static absl::StatusOr<std::unique_ptr<Authenticator>> Create(const std::string& auth_file);

  absl::Status Reload();
  // The caller of `ctx`: its bearer token ("authorization: Bearer TOKEN") if it sent one, otherwise
  // its verified client certificate; UNAUTHENTICATED when neither names a known identity.
  absl::StatusOr<Principal> Authenticate(const grpc::ServerContextBase& ctx) const;
  // The identity of an "authorization" header's value, "Bearer TOKEN" (the HTTP map viewer uses
  // it too); UNAUTHENTICATED when malformed or unknown.
  absl::StatusOr<Principal> AuthenticateBearer(std::string_view authorization) const;
  size_t identities() const;

 private:
  struct Identities {
    std::map<std::string, Principal> token_hashes;  // hex SHA-256 -> principal
    std::map<std::string, Principal> x509_names;     // certificate CN -> principal
    bool any_x509 = false;                            // x509:* given
    Role any_x509_role = Role::kVehicle;
  };
  explicit Authenticator(std::string path) : path_(std::move(path)) {}
  static absl::StatusOr<Identities> Parse(const std::string& path);

  const std::string path_;
  mutable std::shared_mutex mu_;
  Identities identities_;
};

// Authenticates and authorises one call; adds "as=NAME role=ROLE" to its log line. `auth` null:
// authentication off, every caller an anonymous admin. Refusals are UNAUTHENTICATED or
// PERMISSION_DENIED and name what was missing.
absl::StatusOr<Principal> CheckAccess(const Authenticator* auth, const grpc::ServerContextBase& ctx,
                                      Permission permission, RequestLog* log);

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_AUTH_H_
