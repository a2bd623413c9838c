// mapctl: the operator's command-line tool for mapd.
#include <iostream>
#include <string>
#include <vector>

#include "client/mapctl/mapctl.h"

int main(int argc, char** argv) {
  return crowdmap::RunMapctl(std::vector<std::string>(argv + 1, argv + argc), std::cout, std::cerr);
}
