#include "client/api/client_security.h"

#include <cstdlib>
#include <fstream>
#include <sstream>

#include "absl/strings/str_cat.h"
#include "absl/strings/strip.h"

namespace crowdmap {
namespace {

absl::StatusOr<std::string> ReadFile(const std::string& flag, const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::FailedPreconditionError(absl::StrCat("--", flag, ": cannot read ", path));
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

}  // namespace

absl::Status ClientSecurityOptions::Validate() const {
  if (tls_cert.empty() != tls_key.empty()) {
    return absl::InvalidArgumentError("--tls-cert and --tls-key: give both (a client certificate) or neither");
  }
  if (!tls_cert.empty() && tls_ca.empty()) {
    return absl::InvalidArgumentError("--tls-cert: needs --tls-ca (a client certificate is sent over TLS only)");
  }
  if (!tls_server_name.empty() && tls_ca.empty()) {
    return absl::InvalidArgumentError("--tls-server-name: needs --tls-ca");
  }
  if (token.find_first_of("\r\n") != std::string::npos) {
    return absl::InvalidArgumentError("token: must be one line");
  }
  return absl::OkStatus();
}

absl::StatusOr<std::shared_ptr<grpc::ChannelCredentials>> MakeChannelCredentials(const ClientSecurityOptions& options) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  if (options.tls_ca.empty()) return grpc::InsecureChannelCredentials();
  grpc::SslCredentialsOptions ssl;
  absl::StatusOr<std::string> ca = ReadFile("tls-ca", options.tls_ca);
  if (!ca.ok()) return ca.status();
  ssl.pem_root_certs = *ca;
  if (!options.tls_cert.empty()) {
    absl::StatusOr<std::string> cert = ReadFile("tls-cert", options.tls_cert);
    if (!cert.ok()) return cert.status();
    absl::StatusOr<std::string> key = ReadFile("tls-key", options.tls_key);
    if (!key.ok()) return key.status();
    ssl.pem_cert_chain = *cert;
    ssl.pem_private_key = *key;
  }
  return grpc::SslCredentials(ssl);
}

std::map<std::string, bool> ClientSecurityFlags() {
  return {{"tls-ca", true}, {"tls-cert", true}, {"tls-key", true}, {"tls-server-name", true}, {"token-file", true}};
}

absl::Status ApplyClientSecurityFlags(const Flags& flags, ClientSecurityOptions* options) {
  options->tls_ca = flags.GetString("tls-ca", options->tls_ca);
  options->tls_cert = flags.GetString("tls-cert", options->tls_cert);
  options->tls_key = flags.GetString("tls-key", options->tls_key);
  options->tls_server_name = flags.GetString("tls-server-name", options->tls_server_name);
  const char* env_token_file = std::getenv("CROWDMAP_TOKEN_FILE");
  const std::string token_file =
      flags.GetString("token-file", env_token_file != nullptr && *env_token_file ? env_token_file : "");
  if (!token_file.empty()) {
    absl::StatusOr<std::string> token = ReadFile("token-file", token_file);
    if (!token.ok()) return token.status();
    options->token = std::string(absl::StripAsciiWhitespace(*token));
    if (options->token.empty()) return absl::InvalidArgumentError(absl::StrCat("--token-file: ", token_file, " is empty"));
  }
  return options->Validate();
}

std::string ClientSecurityUsage() {
  return R"(  --tls-ca PATH                  TLS: the PEM CA that signed mapd's certificate (default plaintext)
  --tls-cert PATH --tls-key PATH mTLS: this client's PEM certificate and key
  --tls-server-name NAME         the name in mapd's certificate, if not the --server host
  --token-file PATH              bearer token (default $CROWDMAP_TOKEN_FILE; none)
)";
}

}  // namespace crowdmap
