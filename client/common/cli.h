#ifndef CROWDMAP_CLIENT_COMMON_CLI_H_
#define CROWDMAP_CLIENT_COMMON_CLI_H_

#include <memory>
#include <ostream>
#include <string>
#include <string_view>
#include <vector>

#include <CLI/CLI.hpp>

#include "absl/status/statusor.h"
#include "client/common/exit_codes.h"

namespace crowdmap {

// The command line of a tool (mapctl, mapsim) on CLI11, set up alike for each: one subcommand per
// command, a flag given twice takes its last value, --help shows each flag's default and ends with
// `footer` (the exit codes), --version prints "TOOL (crowdmap) VERSION".
std::unique_ptr<CLI::App> NewCommandLine(const std::string& tool, const std::string& description,
                                         const std::string& footer);

enum class ParsedCommandLine { kRunCommand, kPrintedHelpOrVersion };

// Parses `args` (without the program name) into the flags bound to `app`; "help" is --help.
// --help and --version print on `out`. Errors are usage errors naming the command, flag or
// argument: unknown ones, a missing or bad value, and a value that starts with "--" ("--bbox
// --json" is a forgotten value).
absl::StatusOr<ParsedCommandLine> ParseCommandLine(CLI::App& app, const std::vector<std::string>& args,
                                                   std::ostream& out);

// The command ParseCommandLine found, "" when none.
std::string ParsedCommand(const CLI::App& app);

// Validators of a number > 0 and >= 0: "must be > 0, got -1", "expected a number, got 'x'" (CLI11's
// PositiveNumber reads "Value -1 not in range 2.22507e-308 to 1.79769e+308").
CLI::Validator Positive();
CLI::Validator NonNegative();

// Adds the option `name` whose value `parse` turns into `*value` (e.g. ParseNoiseConfig; its errors
// name the field); `*value` keeps its default when the option is not given.
template <typename T>
CLI::Option* AddParsedOption(CLI::App* command, const std::string& name, T* value,
                             absl::StatusOr<T> (*parse)(std::string_view), const std::string& description) {
  return command->add_option_function<std::string>(
      name,
      [name, value, parse](const std::string& text) {
        absl::StatusOr<T> parsed = parse(text);
        if (!parsed.ok()) throw CLI::ValidationError(std::string(parsed.status().message()));
        *value = *std::move(parsed);
      },
      description);
}

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_COMMON_CLI_H_
