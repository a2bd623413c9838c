#include "client/common/client_flags.h"

#include "client/common/exit_codes.h"

namespace crowdmap {

CLI::Option* AddServerFlag(CLI::App* command, std::string* server) {
  return command->add_option("--server", *server, "mapd address")->envname("MAPCTL_SERVER")->type_name("HOST:PORT");
}

void AddClientSecurityFlags(CLI::App* command, ClientSecurityFlags* flags) {
  const std::string group = "TLS and authentication";
  ClientSecurityOptions& o = flags->options;
  command->add_option("--tls-ca", o.tls_ca, "TLS: the PEM CA that signed mapd's certificate (default plaintext)")
      ->type_name("PATH")
      ->group(group);
  command->add_option("--tls-cert", o.tls_cert, "mTLS: this client's PEM certificate, with --tls-key")
      ->type_name("PATH")
      ->group(group);
  command->add_option("--tls-key", o.tls_key, "mTLS: the PEM private key of --tls-cert")->type_name("PATH")->group(group);
  command->add_option("--tls-server-name", o.tls_server_name, "the name in mapd's certificate, if not the --server host")
      ->type_name("NAME")
      ->group(group);
  command->add_option("--token-file", flags->token_file, "file holding the bearer token (default none)")
      ->envname("CROWDMAP_TOKEN_FILE")
      ->type_name("PATH")
      ->group(group);
}

absl::StatusOr<ClientSecurityOptions> ClientSecurityFromFlags(const ClientSecurityFlags& flags) {
  ClientSecurityOptions options = flags.options;
  if (!flags.token_file.empty()) {
    if (absl::Status s = ReadTokenFile(flags.token_file, &options); !s.ok()) return AsUsageError(s);
  }
  if (absl::Status s = options.Validate(); !s.ok()) return AsUsageError(s);
  return options;
}

}  // namespace crowdmap
