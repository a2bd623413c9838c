#ifndef CROWDMAP_SERVER_WEB_ASSETS_H_
#define CROWDMAP_SERVER_WEB_ASSETS_H_

#include <string_view>
#include <vector>

namespace crowdmap {

// One file of the map viewer, compiled into mapd (server/web/ and Debian's libjs-leaflet, read
// at build time by cmake/embed_files.cmake): nothing is loaded from elsewhere at run time.
struct WebAsset {
  std::string_view url_path;      // "/viewer.js"
  std::string_view content_type;  // "text/javascript; charset=utf-8"
  std::string_view body;
};

const std::vector<WebAsset>& WebAssets();

}  // namespace crowdmap

#endif  // CROWDMAP_SERVER_WEB_ASSETS_H_
