#ifndef CROWDMAP_CLIENT_MAPCTL_MAPCTL_H_
#define CROWDMAP_CLIENT_MAPCTL_MAPCTL_H_

#include <ostream>
#include <string>
#include <vector>

namespace crowdmap {

// Runs one mapctl command line (without the program name): results on `out`, one error line on
// `err`. Returns the exit code: 0 success, 1 failure (server, file, unknown id), 2 usage error.
int RunMapctl(const std::vector<std::string>& args, std::ostream& out, std::ostream& err);

}  // namespace crowdmap

#endif  // CROWDMAP_CLIENT_MAPCTL_MAPCTL_H_
