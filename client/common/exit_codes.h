#ifndef CROWDMAP_CLIENT_COMMON_FLAGS_H_
#define CROWDMAP_CLIENT_COMMON_FLAGS_H_

#include <map>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace crowdmap {

// Exit codes of the command-line tools (mapctl, mapsim), as their --help documents.
constexpr int kExitOk = 0;
constexpr int kExitFailure = 1;  // a failed call, file or computation
constexpr int kExitUsage = 2;    // unknown command or flag, missing argument, bad value

// A usage error: INVALID_ARGUMENT marked so that the tools exit with kExitUsage for it, while an
// INVALID_ARGUMENT from the server (a failed call) still exits with kExitFailure.
absl::Status UsageError(absl::string_view message);
// `status` marked as a usage error (OK stays OK).
absl::Status AsUsageError(absl::Status status);
bool IsUsageError(const absl::Status& status);
// kExitOk, kExitUsage for a usage error, else kExitFailure.
int ExitCodeFor(const absl::Status& status);

// Command-line flags of one subcommand: "--name value", "--name=value" and boolean "--name".
// Unknown flags are errors, so typos do not pass silently. Parse and Get* errors are usage errors.
class Flags {
 public:
  // `known` maps each accepted flag to true when it takes a value, false for a boolean switch.
  static absl::StatusOr<Flags> Parse(const std::vector<std::string>& args, const std::map<std::string, bool>& known);

  bool Has(const std::string& name) const { return values_.count(name) > 0; }
  std::string GetString(const std::string& name, const std::string& fallback) const;
  absl::StatusOr<long long> GetInt(const std::string& name, long long fallback) const;
  absl::StatusOr<double> GetDouble(const std::string& name, double fallback) const;
  const std::vector<std::string>& positional() const { return positional_; }

 private:
  std::map<std::string, std::string> values_;
  std::vector<std::string> positional_;
};

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_COMMON_FLAGS_H_
