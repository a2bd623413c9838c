#include "client/common/cli.h"

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"

namespace crowdmap {
namespace {

// CLI11 takes the argument after a flag as its value, whatever it looks like; one that starts
// with "--" is a forgotten value ("--bbox --json"), refused rather than taken.
void RefuseFlagsAsValues(CLI::App* app) {
  static const CLI::Validator kNotAFlag(
      [](std::string& value) {
        return absl::StartsWith(value, "--") ? absl::StrCat("needs a value, not the flag ", value) : std::string();
      },
      "");
  for (CLI::Option* option : app->get_options()) {
    if (!option->get_positional() && option->get_type_size_max() > 0) option->check(kNotAFlag);
  }
  for (CLI::App* command : app->get_subcommands({})) RefuseFlagsAsValues(command);
}

CLI::Validator NumberAtLeastZero(bool zero_allowed) {
  return CLI::Validator(
      [zero_allowed](std::string& text) {
        double value = 0.0;
        if (!absl::SimpleAtod(text, &value)) return absl::StrCat("expected a number, got '", text, "'");
        if (zero_allowed ? value >= 0.0 : value > 0.0) return std::string();
        return absl::StrCat("must be ", zero_allowed ? ">=" : ">", " 0, got ", text);
      },
      "");
}

bool HasCommand(CLI::App& app, const std::string& name) {
  for (const CLI::App* command : app.get_subcommands({})) {
    if (command->check_name(name)) return true;
  }
  return false;
}

}  // namespace

std::unique_ptr<CLI::App> NewCommandLine(const std::string& tool, const std::string& description,
                                         const std::string& footer) {
  auto app = std::make_unique<CLI::App>(description, tool);
  // Inherited by the commands added later.
  app->option_defaults()->always_capture_default()->multi_option_policy(CLI::MultiOptionPolicy::TakeLast);
  app->footer(footer);
  app->get_formatter()->column_width(34);
  app->set_version_flag("--version", absl::StrCat(tool, " (crowdmap) ", CROWDMAP_VERSION));
  app->require_subcommand(1);
  return app;
}

CLI::Validator Positive() { return NumberAtLeastZero(/*zero_allowed=*/false); }

CLI::Validator NonNegative() { return NumberAtLeastZero(/*zero_allowed=*/true); }

absl::StatusOr<ParsedCommandLine> ParseCommandLine(CLI::App& app, const std::vector<std::string>& args,
                                                   std::ostream& out) {
  std::vector<std::string> reversed(args.rbegin(), args.rend());  // CLI11 takes the arguments from the back
  if (!reversed.empty() && reversed.back() == "help") reversed.back() = "--help";
  if (!args.empty() && !absl::StartsWith(args[0], "-") && args[0] != "help" && !HasCommand(app, args[0])) {
    return UsageError(absl::StrCat("unknown command '", args[0], "'"));
  }
  RefuseFlagsAsValues(&app);
  try {
    app.parse(reversed);
  } catch (const CLI::CallForHelp&) {
    out << app.help();
    return ParsedCommandLine::kPrintedHelpOrVersion;
  } catch (const CLI::CallForVersion& version) {
    out << version.what() << "\n";
    return ParsedCommandLine::kPrintedHelpOrVersion;
  } catch (const CLI::ParseError& e) {
    return UsageError(e.what());
  }
  return ParsedCommandLine::kRunCommand;
}

std::string ParsedCommand(const CLI::App& app) {
  const std::vector<CLI::App*> commands = app.get_subcommands();
  return commands.empty() ? "" : commands.front()->get_name();
}

}  // namespace crowdmap
