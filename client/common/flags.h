#ifndef CROWDMAP_CLIENT_COMMON_FLAGS_H_
#define CROWDMAP_CLIENT_COMMON_FLAGS_H_

#include <map>
#include <string>
#include <vector>

#include "absl/status/statusor.h"

namespace crowdmap {

// Command-line flags of one subcommand: "--name value", "--name=value" and boolean "--name".
// Unknown flags are errors, so typos do not pass silently.
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
