#include "server/auth.h"

#include <openssl/evp.h>

#include <fstream>
#include <sstream>

#include <grpcpp/security/auth_context.h>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"
#include "core/model/passage.h"

namespace crowdmap {
namespace {

absl::StatusOr<std::string> ReadPem(const std::string& flag, const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::FailedPreconditionError(absl::StrCat("--", flag, ": cannot read ", path));
  std::stringstream text;
  text << in.rdbuf();
  if (!absl::StrContains(text.str(), "-----BEGIN ")) {
    return absl::FailedPreconditionError(absl::StrCat("--", flag, ": ", path, " holds no PEM block"));
  }
  return text.str();
}

absl::StatusOr<Role> ParseRole(absl::string_view name) {
  if (name == "vehicle") return Role::kVehicle;
  if (name == "operator") return Role::kOperator;
  if (name == "admin") return Role::kAdmin;
  return absl::InvalidArgumentError(absl::StrCat("role '", name, "' is not vehicle, operator or admin"));
}

bool IsHex64(absl::string_view s) {
  if (s.size() != 64) return false;
  for (char c : s) {
    if (!absl::ascii_isxdigit(static_cast<unsigned char>(c))) return false;
  }
  return true;
}

}  // namespace

absl::Status SecurityOptions::Validate() const {
  for (const auto& [flag, value] : {std::pair<const char*, const std::string&>{"auth", auth}, {"reflection", reflection}}) {
    if (value != "auto" && value != "on" && value != "off") {
      return absl::InvalidArgumentError(absl::StrCat("--", flag, ": must be auto, on or off, got '", value, "'"));
    }
  }
  if (tls_cert.empty() != tls_key.empty()) {
    return absl::InvalidArgumentError("--tls-cert and --tls-key: give both (TLS) or neither (plaintext)");
  }
  if (!tls_client_ca.empty() && tls_cert.empty()) {
    return absl::InvalidArgumentError("--tls-client-ca: needs --tls-cert and --tls-key (mTLS runs over TLS)");
  }
  return absl::OkStatus();
}

bool IsLoopbackListen(const std::string& listen) {
  if (absl::StartsWith(listen, "unix:") || absl::StartsWith(listen, "unix-abstract:")) return true;
  std::string host = listen;
  if (const size_t colon = listen.rfind(':'); colon != std::string::npos) host = listen.substr(0, colon);
  if (absl::StartsWith(host, "ipv4:")) host = host.substr(5);
  if (absl::StartsWith(host, "ipv6:")) host = host.substr(5);
  if (host == "localhost" || host == "[::1]" || host == "::1") return true;
  return absl::StartsWith(host, "127.");
}

bool AuthEnabled(const SecurityOptions& options, const std::string& listen) {
  if (options.auth == "on") return true;
  if (options.auth == "off") return false;
  return !IsLoopbackListen(listen);
}

bool ReflectionEnabled(const SecurityOptions& options, const std::string& listen) {
  if (options.reflection == "on") return true;
  if (options.reflection == "off") return false;
  return !AuthEnabled(options, listen);
}

absl::StatusOr<std::shared_ptr<grpc::ServerCredentials>> MakeServerCredentials(const SecurityOptions& options) {
  if (!options.tls()) return grpc::InsecureServerCredentials();
  absl::StatusOr<std::string> cert = ReadPem("tls-cert", options.tls_cert);
  if (!cert.ok()) return cert.status();
  absl::StatusOr<std::string> key = ReadPem("tls-key", options.tls_key);
  if (!key.ok()) return key.status();
  grpc::SslServerCredentialsOptions ssl;
  ssl.pem_key_cert_pairs.push_back({*key, *cert});
  if (!options.tls_client_ca.empty()) {
    absl::StatusOr<std::string> ca = ReadPem("tls-client-ca", options.tls_client_ca);
    if (!ca.ok()) return ca.status();
    ssl.pem_root_certs = *ca;
    // With an auth file, clients may also come with a token instead of a certificate; a
    // certificate they present is verified either way.
    ssl.client_certificate_request = options.auth_file.empty()
                                         ? GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY
                                         : GRPC_SSL_REQUEST_CLIENT_CERTIFICATE_AND_VERIFY;
  }
  return grpc::SslServerCredentials(ssl);
}

const char* RoleName(Role role) {
  switch (role) {
    case Role::kVehicle:
      return "vehicle";
    case Role::kOperator:
      return "operator";
    case Role::kAdmin:
      return "admin";
  }
  return "?";
}

absl::Status Principal::MayActFor(const std::string& vehicle_id) const {
  if (role == Role::kAdmin || (role == Role::kVehicle && vehicle_id == name)) return absl::OkStatus();
  if (role == Role::kOperator) {
    return absl::PermissionDeniedError(absl::StrCat("vehicle_id: '", name, "' is an operator: operators read, they do not upload"));
  }
  // (an identifier no upload could carry is not echoed)
  const std::string named = ValidateId("vehicle_id", vehicle_id).ok() ? absl::StrCat("'", vehicle_id, "'")
                                                                       : std::string("(not a valid one)");
  return absl::PermissionDeniedError(
      absl::StrCat("vehicle_id: ", named, " is not the authenticated vehicle '", name, "'"));
}

std::string Sha256Hex(const std::string& text) {
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int length = 0;
  EVP_Digest(text.data(), text.size(), digest, &length, EVP_sha256(), nullptr);
  static constexpr char kHex[] = "0123456789abcdef";
  std::string out;
  for (unsigned int i = 0; i < length; ++i) {
    out += kHex[digest[i] >> 4];
    out += kHex[digest[i] & 15];
  }
  return out;
}

absl::StatusOr<Authenticator::Identities> Authenticator::Parse(const std::string& path) {
  Identities ids;
  if (path.empty()) return ids;
  std::ifstream in(path);
  if (!in) return absl::FailedPreconditionError(absl::StrCat("--auth-file: cannot read ", path));
  std::string line;
  int number = 0;
  while (std::getline(in, line)) {
    ++number;
    absl::string_view text = line;
    if (const size_t hash = text.find('#'); hash != absl::string_view::npos) text = text.substr(0, hash);
    const std::vector<absl::string_view> fields = absl::StrSplit(text, absl::ByAnyChar(" \t"), absl::SkipWhitespace());
    if (fields.empty()) continue;
    const std::string where = absl::StrCat("--auth-file: ", path, ":", number, ": ");
    if (fields.size() != 3) return absl::InvalidArgumentError(absl::StrCat(where, "expected \"sha256:HEX|x509:CN ROLE NAME\""));
    absl::StatusOr<Role> role = ParseRole(fields[1]);
    if (!role.ok()) return absl::InvalidArgumentError(absl::StrCat(where, role.status().message()));
    absl::string_view key = fields[0];
    if (absl::ConsumePrefix(&key, "sha256:")) {
      if (!IsHex64(key)) return absl::InvalidArgumentError(absl::StrCat(where, "sha256: needs 64 hex digits"));
      ids.token_hashes[absl::AsciiStrToLower(key)] = Principal{std::string(fields[2]), *role, "token"};
    } else if (absl::ConsumePrefix(&key, "x509:")) {
      if (key == "*") {
        if (fields[2] != "*") return absl::InvalidArgumentError(absl::StrCat(where, "x509:* takes the name * (the certificate's CN)"));
        ids.any_x509 = true;
        ids.any_x509_role = *role;
      } else if (key.empty()) {
        return absl::InvalidArgumentError(absl::StrCat(where, "x509: needs a certificate common name"));
      } else {
        ids.x509_names[std::string(key)] = Principal{std::string(fields[2]), *role, "x509"};
      }
    } else {
      return absl::InvalidArgumentError(absl::StrCat(where, "an identity starts with sha256: or x509:"));
    }
  }
  return ids;
}

absl::StatusOr<std::unique_ptr<Authenticator>> Authenticator::Create(const std::string& auth_file) {
  std::unique_ptr<Authenticator> auth(new Authenticator(auth_file));
  if (absl::Status s = auth->Reload(); !s.ok()) return s;
  return auth;
}

absl::Status Authenticator::Reload() {
  absl::StatusOr<Identities> ids = Parse(path_);
  if (!ids.ok()) return ids.status();
  std::unique_lock lock(mu_);
  identities_ = *std::move(ids);
  return absl::OkStatus();
}

size_t Authenticator::identities() const {
  std::shared_lock lock(mu_);
  return identities_.token_hashes.size() + identities_.x509_names.size() + (identities_.any_x509 ? 1 : 0);
}

absl::StatusOr<Principal> Authenticator::Authenticate(const grpc::ServerContextBase& ctx) const {
  const auto& metadata = ctx.client_metadata();
  if (auto it = metadata.find("authorization"); it != metadata.end()) {
    return AuthenticateBearer(std::string_view(it->second.data(), it->second.size()));
  }
  const std::shared_ptr<const grpc::AuthContext> auth = ctx.auth_context();
  if (auth != nullptr && auth->IsPeerAuthenticated()) {
    for (const grpc::string_ref& cn : auth->FindPropertyValues("x509_common_name")) {
      const std::string name(cn.data(), cn.size());
      std::shared_lock lock(mu_);
      if (auto found = identities_.x509_names.find(name); found != identities_.x509_names.end()) return found->second;
      if (identities_.any_x509) return Principal{name, identities_.any_x509_role, "x509"};
      return absl::UnauthenticatedError(absl::StrCat("client certificate CN '", name, "' is not in the auth file"));
    }
  }
  return absl::UnauthenticatedError(
      "no credentials: send 'authorization: Bearer TOKEN' metadata (--token-file) or a client certificate");
}

absl::StatusOr<Principal> Authenticator::AuthenticateBearer(std::string_view authorization) const {
  absl::string_view value(authorization.data(), authorization.size());
  if (!absl::ConsumePrefix(&value, "Bearer ") || value.empty()) {
    return absl::UnauthenticatedError("authorization: expected 'Bearer TOKEN'");
  }
  const std::string hash = Sha256Hex(std::string(value));
  std::shared_lock lock(mu_);
  auto found = identities_.token_hashes.find(hash);
  if (found == identities_.token_hashes.end()) return absl::UnauthenticatedError("authorization: unknown token");
  return found->second;
}

absl::StatusOr<Principal> CheckAccess(const Authenticator* auth, const grpc::ServerContextBase& ctx,
                                      Permission permission, RequestLog* log) {
  if (auth == nullptr) return Principal{"anonymous", Role::kAdmin, "none"};
  absl::StatusOr<Principal> who = auth->Authenticate(ctx);
  if (!who.ok()) return who.status();
  log->Add(absl::StrCat("as=", who->name, " role=", RoleName(who->role)));
  switch (permission) {
    case Permission::kReadMap:
    case Permission::kReadPassages:  // a vehicle's own passages only: the handler checks MayActFor
      return who;
    case Permission::kUpload:
      if (who->role == Role::kOperator) {
        return absl::PermissionDeniedError("role operator: may read the map and the passages, not upload");
      }
      return who;
    case Permission::kAdministrate:
      if (who->role != Role::kAdmin) {
        return absl::PermissionDeniedError(absl::StrCat("role ", RoleName(who->role), ": this RPC needs role admin"));
      }
      return who;
  }
  return absl::PermissionDeniedError("unknown permission");
}

}  // namespace crowdmap
