// mapd: serves the map until SIGTERM/SIGINT, then shuts down in order and exits 0; SIGHUP reloads
// the auth file.
#include <pthread.h>
#include <signal.h>

#include <iostream>

#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include "core/logging/log_format.h"
#include "server/log_format.h"
#include "server/map_server.h"
#include "server/mapd_config.h"

int main(int argc, char** argv) {
  crowdmap::TuneProcessForServing();
  // Block the shutdown signals in every thread; the main thread takes them with sigwait.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGTERM);
  sigaddset(&signals, SIGINT);
  sigaddset(&signals, SIGHUP);  // reload the auth file
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);

  std::vector<std::string> args(argv + 1, argv + argc);
  auto config = crowdmap::ParseMapdConfig(args);
  if (!config.ok()) {
    std::cerr << "mapd: " << config.status().message() << "\n";
    return 2;
  }
  if (config->help) {
    std::cout << crowdmap::MapdUsage();
    return 0;
  }
  if (config->version) {
    std::cout << "mapd (crowdmap) " << CROWDMAP_VERSION << "\n";
    return 0;
  }
  auto logger = spdlog::stderr_color_mt("mapd");
  spdlog::set_default_logger(logger);
  if (config->log_format == "json") {
    spdlog::set_formatter(crowdmap::MakeJsonLogFormatter());
  } else {
    crowdmap::UseTextLogFormat(*logger);
  }
  const auto level = spdlog::level::from_str(config->log_level);
  if (level == spdlog::level::off && config->log_level != "off") {
    std::cerr << "mapd: --log-level: unknown level '" << config->log_level << "'\n";
    return 2;
  }
  spdlog::set_level(level);
  spdlog::flush_on(spdlog::level::info);
  spdlog::info("event=settings version={} {}", CROWDMAP_VERSION, crowdmap::DescribeMapdConfig(*config));
  for (const std::string& caveat : crowdmap::MapdConfigCaveats(*config)) {
    spdlog::warn("event=settings_caveat caveat=\"{}\"", caveat);  // no double quotes inside
  }

  auto server = crowdmap::MapServer::Start(config->server);
  if (!server.ok()) {
    spdlog::critical("event=start_failed error=\"{}\"", server.status().ToString());
    return 1;
  }
  int signal_number = 0;
  while (sigwait(&signals, &signal_number) == 0 && signal_number == SIGHUP) {
    spdlog::info("event=signal signal=SIGHUP");
    if ((*server)->auth_enabled()) (void)(*server)->ReloadAuth();
  }
  spdlog::info("event=signal signal={}", signal_number == SIGTERM ? "SIGTERM" : "SIGINT");
  (*server)->Shutdown();
  server->reset();
  return 0;
}
