#include "client/mapctl/mapctl.h"

#include <cmath>
#include <fstream>
#include <map>
#include <memory>
#include <optional>

#include <google/protobuf/util/json_util.h>
#include <nlohmann/json.hpp>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_replace.h"
#include "absl/strings/str_split.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "core/geo/tiles.h"
#include "server/geojson.h"
#include "client/api/localization_export.h"
#include "client/api/map_client.h"
#include "client/api/passage_files.h"
#include "client/common/cli.h"
#include "client/common/client_flags.h"
#include "client/mapctl/table_cell.h"

namespace crowdmap {
namespace {

constexpr char kExitCodes[] = R"(Exit codes: 0 success, 1 failure (unreachable server, malformed file, unknown id, ...), 2 usage error
(unknown command or flag, missing argument, bad value), reported before any call is made.)";

// A command's flags and arguments, as parsed (each command binds those it takes).
struct Arguments {
  std::vector<std::string> positional;
  std::string server = MapClientOptions().server;
  bool json = false;
  double deadline_s = 10.0;
  ClientSecurityFlags security;
  std::string state, bbox, at, out;
  std::string format;  // each command's default is set where it binds --format
  int64_t since = 0, updates = 0;
  double seconds = 0.0;
  bool ellipses = false;
};

struct Context {
  std::unique_ptr<MapClient> client;
  bool json = false;
  std::ostream* out = nullptr;
  std::ostream* err = nullptr;  // warnings, one line each, prefixed with the command
  std::string command;

  std::ostream& Warn() { return *err << "mapctl " << command << ": "; }
};

std::string OneLine(absl::string_view message) {
  return absl::StrReplaceAll(message, {{"\n", " "}, {"\r", " "}});
}

std::string ToJson(const google::protobuf::Message& message) {
  std::string text;
  google::protobuf::util::JsonPrintOptions options;
  options.add_whitespace = true;
  options.preserve_proto_field_names = true;
  options.always_print_primitive_fields = true;  // a zero count or version is printed, not left out
  (void)google::protobuf::util::MessageToJsonString(message, &text, options);
  return text;
}

std::string StateName(pb::PassageState state) {
  switch (state) {
    case pb::PASSAGE_STATE_QUEUED: return "queued";
    case pb::PASSAGE_STATE_PROCESSING: return "processing";
    case pb::PASSAGE_STATE_APPLIED: return "applied";
    case pb::PASSAGE_STATE_REJECTED: return "rejected";
    case pb::PASSAGE_STATE_FAILED: return "failed";
    case pb::PASSAGE_STATE_EXCLUDED: return "excluded";
    case pb::PASSAGE_STATE_QUARANTINED: return "quarantined";
    case pb::PASSAGE_STATE_DISCARDED: return "discarded";
    default: return "unspecified";
  }
}

absl::StatusOr<pb::PassageState> ParseState(const std::string& name) {
  for (pb::PassageState s : {pb::PASSAGE_STATE_QUEUED, pb::PASSAGE_STATE_PROCESSING, pb::PASSAGE_STATE_APPLIED,
                             pb::PASSAGE_STATE_REJECTED, pb::PASSAGE_STATE_FAILED, pb::PASSAGE_STATE_EXCLUDED,
                             pb::PASSAGE_STATE_QUARANTINED, pb::PASSAGE_STATE_DISCARDED}) {
    if (StateName(s) == name) return s;
  }
  return UsageError(absl::StrCat(
      "--state: '", name,
      "' is not queued, processing, applied, rejected, failed, excluded, quarantined or discarded"));
}

std::string FormatTime(int64_t unix_ms) {
  if (unix_ms <= 0) return "-";
  return absl::FormatTime("%Y-%m-%d %H:%M:%S", absl::FromUnixMillis(unix_ms), absl::UTCTimeZone());
}

bool InBboxRange(double min_lon, double min_lat, double max_lon, double max_lat) {
  return min_lon <= max_lon && min_lat <= max_lat && min_lon >= -180 && max_lon <= 180 && min_lat >= -90 &&
         max_lat <= 90;
}

// --bbox MINLON,MINLAT,MAXLON,MAXLAT. A box valid only with lat and lon swapped (a latitude beyond
// +-90 that is a valid longitude) is read swapped, with a warning; a box valid neither way
// is a usage error.
absl::StatusOr<pb::BoundingBox> ParseBbox(const Arguments& args, Context& ctx) {
  const std::string& text = args.bbox;
  std::vector<std::string> parts = absl::StrSplit(text, ',');
  double v[4];
  if (parts.size() != 4) return UsageError(absl::StrCat("--bbox: '", text, "' is not MINLON,MINLAT,MAXLON,MAXLAT"));
  for (int i = 0; i < 4; ++i) {
    if (!absl::SimpleAtod(parts[i], &v[i]) || !std::isfinite(v[i])) {
      return UsageError(absl::StrCat("--bbox: '", parts[i], "' is not a number"));
    }
  }
  pb::BoundingBox box;
  if (InBboxRange(v[0], v[1], v[2], v[3])) {
    box.set_min_lon_deg(v[0]);
    box.set_min_lat_deg(v[1]);
    box.set_max_lon_deg(v[2]);
    box.set_max_lat_deg(v[3]);
    return box;
  }
  const bool lat_out_of_range = std::abs(v[1]) > 90 || std::abs(v[3]) > 90;
  if (lat_out_of_range && InBboxRange(v[1], v[0], v[3], v[2])) {
    ctx.Warn() << absl::StrFormat("warning: --bbox %s has a latitude beyond +-90 and reads as a box only with lat and lon "
                            "swapped; using MINLON,MINLAT,MAXLON,MAXLAT = %s,%s,%s,%s\n",
                            text, parts[1], parts[0], parts[3], parts[2]);
    box.set_min_lon_deg(v[1]);
    box.set_min_lat_deg(v[0]);
    box.set_max_lon_deg(v[3]);
    box.set_max_lat_deg(v[2]);
    return box;
  }
  if (v[0] > v[2] || v[1] > v[3]) return UsageError("--bbox: need MINLON <= MAXLON and MINLAT <= MAXLAT");
  return UsageError(absl::StrCat("--bbox: '", text, "' cannot be a box, either way round: longitudes must lie in "
                                 "[-180, 180], latitudes in [-90, 90]"));
}

void PrintLandmarkTable(const std::vector<pb::Landmark>& landmarks, std::ostream& out) {
  out << absl::StrFormat("%8s %13s %14s %9s %9s %9s %8s %7s\n", "ID", "LAT", "LON", "SIGMA_E", "SIGMA_N", "ELL95_M",
                         "VERSION", "SEEN");
  for (const pb::Landmark& l : landmarks) {
    Eigen::Matrix2d cov;
    cov << l.cov_en_m2().ee(), l.cov_en_m2().en(), l.cov_en_m2().ne(), l.cov_en_m2().nn();
    out << absl::StrFormat("%8d %13.8f %14.8f %9.3f %9.3f %9.3f %8d %7d\n", l.id(), l.lat_deg(), l.lon_deg(),
                           std::sqrt(cov(0, 0)), std::sqrt(cov(1, 1)), ErrorEllipse95(cov).semi_major_m, l.version(),
                           l.passages_seen());
  }
}

void PrintPassageRow(const pb::PassageStatus& p, std::ostream& out) {
  out << absl::StrFormat("%8d  %s %s %-10s %8d  %-19s  %s\n", p.id(), TableCell(p.vehicle_id(), 14),
                         TableCell(p.passage_id(), 16), StateName(p.state()), p.attempts(),
                         FormatTime(p.received_unix_ms()), EscapeForTerminal(OneLine(p.error())));
}

absl::Status Upload(const Arguments& args, Context& ctx) {
  if (args.positional.empty()) return UsageError("give at least one passage file");
  std::vector<std::pair<std::string, pb::Passage>> files;
  for (const std::string& path : args.positional) {
    absl::StatusOr<pb::Passage> passage = ReadPassageFile(path);
    if (!passage.ok()) return passage.status();
    files.emplace_back(path, *std::move(passage));
  }
  if (!ctx.json) *ctx.out << absl::StrFormat("%-32s %8s  %-14s %-16s %-10s %s\n", "FILE", "ID", "VEHICLE", "PASSAGE", "STATE", "DUPLICATE");
  // A file the server refuses for what it holds (invalid, the same drive as an earlier upload) is
  // reported and the others are still sent; anything else (unreachable, not allowed, queue full)
  // stops here, since the files after it would fare no better.
  int refused = 0;
  absl::Status first_refusal;
  for (const auto& [path, passage] : files) {
    absl::StatusOr<pb::UploadPassageResponse> response = ctx.client->Upload(passage);
    if (!response.ok()) {
      const absl::Status status(response.status().code(), absl::StrCat(path, ": ", response.status().message()));
      const absl::StatusCode code = status.code();
      if (code != absl::StatusCode::kInvalidArgument && code != absl::StatusCode::kAlreadyExists) return status;
      ctx.Warn() << EscapeForTerminal(OneLine(status.ToString())) << "\n";
      if (refused++ == 0) first_refusal = status;
      continue;
    }
    if (ctx.json) {
      *ctx.out << ToJson(*response);
    } else {
      const pb::PassageStatus& s = response->status();
      *ctx.out << absl::StrFormat("%s %8d  %s %s %-10s %s\n", TableCell(path, 32), s.id(), TableCell(s.vehicle_id(), 14),
                                  TableCell(s.passage_id(), 16), StateName(s.state()),
                                  response->duplicate() ? "yes" : "no");
    }
  }
  if (refused == 0) return absl::OkStatus();
  return absl::Status(first_refusal.code(), absl::StrCat(refused, " of ", files.size(), " files refused, the first ",
                                                         first_refusal.message()));
}

// The passage named by a command's one argument: a server id, or VEHICLE/PASSAGE_ID.
absl::StatusOr<PassageKey> PassageArgument(const Arguments& args) {
  if (args.positional.size() != 1) {
    return UsageError(absl::StrCat("give one ID (number or VEHICLE/PASSAGE_ID)"));
  }
  const std::string& arg = args.positional[0];
  PassageKey key;
  if (absl::SimpleAtoi(arg, &key.id)) return key;
  if (size_t slash = arg.find('/'); slash != std::string::npos) {
    key.vehicle_id = arg.substr(0, slash);
    key.passage_id = arg.substr(slash + 1);
    return key;
  }
  return UsageError(absl::StrCat("'", arg, "' is neither a number nor VEHICLE/PASSAGE_ID"));
}

absl::Status Status(const Arguments& args, Context& ctx) {
  absl::StatusOr<PassageKey> key = PassageArgument(args);
  if (!key.ok()) return key.status();
  absl::StatusOr<pb::PassageStatus> status =
      key->id != 0 ? ctx.client->GetPassage(key->id) : ctx.client->GetPassage(key->vehicle_id, key->passage_id);
  if (!status.ok()) return status.status();
  if (ctx.json) {
    *ctx.out << ToJson(*status);
    return absl::OkStatus();
  }
  std::ostream& out = *ctx.out;
  out << absl::StrFormat("id:          %d\nvehicle:     %s\npassage:     %s\nstate:       %s\nattempts:    %d\n"
                         "received:    %s\nfinished:    %s\nsize:        %d bytes\n",
                         status->id(), EscapeForTerminal(status->vehicle_id()),
                         EscapeForTerminal(status->passage_id()), StateName(status->state()),
                         status->attempts(), FormatTime(status->received_unix_ms()),
                         FormatTime(status->finished_unix_ms()), status->size_bytes());
  if (!status->error().empty()) out << "error:       " << EscapeForTerminal(OneLine(status->error())) << "\n";
  if (status->payload_pruned_unix_ms() > 0) {
    out << "upload:      deleted " << FormatTime(status->payload_pruned_unix_ms())
        << " (its factors were folded into the map's base)\n";
  }
  if (status->has_result()) {
    const pb::PassageResult& r = status->result();
    out << absl::StrFormat("result:      strategy=%s nodes=%d subgraphs=%d updated=%d created=%d conditioned=%d "
                           "detections_used=%d total_ms=%.1f map_version=%d\n",
                           r.strategy(), r.nodes(), r.subgraphs(), r.landmarks_updated(), r.landmarks_created(),
                           r.landmarks_conditioned(), r.detections_used(), r.total_ms(), r.map_version());
  }
  return absl::OkStatus();
}

absl::Status LandmarkCommand(const Arguments& args, Context& ctx) {
  int64_t id = 0;
  if (args.positional.size() != 1 || !absl::SimpleAtoi(args.positional[0], &id)) {
    return UsageError("give one landmark id (a number)");
  }
  absl::StatusOr<pb::GetLandmarkResponse> response = ctx.client->GetLandmark(id);
  if (!response.ok()) return response.status();
  if (ctx.json) {
    *ctx.out << ToJson(*response);
    return absl::OkStatus();
  }
  const pb::Landmark& l = response->landmark();
  *ctx.out << absl::StrFormat(
      "id:          %d\nposition:    %.8f, %.8f\nsigma:       %.3f m East, %.3f m North\nversion:     %d\n"
      "seen by:     %d passages\n",
      l.id(), l.lat_deg(), l.lon_deg(), std::sqrt(l.cov_en_m2().ee()), std::sqrt(l.cov_en_m2().nn()), l.version(),
      l.passages_seen());
  *ctx.out << absl::StrFormat("shaped by:   %d passages retained apart (older ones are folded into the map)\n",
                              response->passages_size());
  for (const pb::PassageKey& p : response->passages()) {
    *ctx.out << "  " << EscapeForTerminal(p.vehicle_id()) << "/" << EscapeForTerminal(p.passage_id()) << "\n";
  }
  return absl::OkStatus();
}

constexpr double kDeg = 180.0 / M_PI;

// "camera yaw +0.52° ± 0.03° after 14 passages"
std::string DescribeVehicleYaw(const pb::Vehicle& v) {
  return absl::StrFormat("camera yaw %+.2f° ± %.2f° after %d passage%s", v.camera_yaw_offset_rad() * kDeg,
                         v.camera_yaw_sigma_rad() * kDeg, v.passages(), v.passages() == 1 ? "" : "s");
}

absl::Status Vehicles(const Arguments& args, Context& ctx) {
  if (args.positional.size() > 1) return UsageError("give at most one vehicle id");
  if (args.positional.size() == 1) {
    absl::StatusOr<pb::Vehicle> vehicle = ctx.client->GetVehicle(args.positional[0]);
    if (!vehicle.ok()) return vehicle.status();
    *ctx.out << (ctx.json ? ToJson(*vehicle)
                          : absl::StrCat(EscapeForTerminal(vehicle->vehicle_id()), ": ", DescribeVehicleYaw(*vehicle),
                                         " (map version ", vehicle->map_version(), ")\n"));
    return absl::OkStatus();
  }
  absl::StatusOr<pb::ListVehiclesResponse> list = ctx.client->ListVehicles();
  if (!list.ok()) return list.status();
  if (ctx.json) {
    *ctx.out << ToJson(*list);
    return absl::OkStatus();
  }
  *ctx.out << absl::StrFormat("%d vehicles\n", list->vehicles_size());
  for (const pb::Vehicle& v : list->vehicles()) {
    *ctx.out << EscapeForTerminal(v.vehicle_id()) << ": " << DescribeVehicleYaw(v) << "\n";
  }
  return absl::OkStatus();
}

absl::Status Exclude(const Arguments& args, Context& ctx) {
  absl::StatusOr<PassageKey> key = PassageArgument(args);
  if (!key.ok()) return key.status();
  absl::StatusOr<pb::ExcludePassageResponse> response = ctx.client->ExcludePassage(*key);
  if (!response.ok()) return response.status();
  if (ctx.json) {
    *ctx.out << ToJson(*response);
    return absl::OkStatus();
  }
  *ctx.out << absl::StrFormat("passage %d (%s/%s) excluded: map version %d, %d landmarks re-estimated, %d removed, "
                              "%d moved through their correlation\n",
                              response->status().id(), EscapeForTerminal(response->status().vehicle_id()),
                              EscapeForTerminal(response->status().passage_id()), response->map_version(), response->landmarks_updated(),
                              response->landmarks_removed(), response->landmarks_conditioned());
  return absl::OkStatus();
}

// requeue ID / release ID / discard ID: an operator's decision on a failed or quarantined passage.
absl::Status Resolve(pb::ResolvePassageRequest::Action action, const Arguments& args, Context& ctx) {
  absl::StatusOr<PassageKey> key = PassageArgument(args);
  if (!key.ok()) return key.status();
  absl::StatusOr<pb::PassageStatus> status = ctx.client->ResolvePassage(*key, action);
  if (!status.ok()) return status.status();
  if (ctx.json) {
    *ctx.out << ToJson(*status);
    return absl::OkStatus();
  }
  *ctx.out << absl::StrFormat("passage %d (%s/%s) is now %s\n", status->id(), EscapeForTerminal(status->vehicle_id()),
                              EscapeForTerminal(status->passage_id()), StateName(status->state()));
  return absl::OkStatus();
}

absl::Status Requeue(const Arguments& args, Context& ctx) {
  return Resolve(pb::ResolvePassageRequest::REQUEUE, args, ctx);
}

absl::Status Release(const Arguments& args, Context& ctx) {
  return Resolve(pb::ResolvePassageRequest::RELEASE, args, ctx);
}

absl::Status Discard(const Arguments& args, Context& ctx) {
  return Resolve(pb::ResolvePassageRequest::DISCARD, args, ctx);
}

absl::Status Passages(const Arguments& args, Context& ctx) {
  std::optional<pb::PassageState> state;
  if (!args.state.empty()) {
    absl::StatusOr<pb::PassageState> s = ParseState(args.state);
    if (!s.ok()) return s.status();
    state = *s;
  }
  absl::StatusOr<std::vector<pb::PassageStatus>> list = ctx.client->ListPassages(state);
  if (!list.ok()) return list.status();
  if (ctx.json) {
    pb::ListPassagesResponse response;
    for (const pb::PassageStatus& p : *list) *response.add_passages() = p;
    *ctx.out << ToJson(response);
    return absl::OkStatus();
  }
  *ctx.out << absl::StrFormat("%8s  %-14s %-16s %-10s %8s  %-19s  %s\n", "ID", "VEHICLE", "PASSAGE", "STATE",
                              "ATTEMPTS", "RECEIVED (UTC)", "ERROR");
  for (const pb::PassageStatus& p : *list) PrintPassageRow(p, *ctx.out);
  *ctx.out << list->size() << " passages\n";
  return absl::OkStatus();
}

absl::Status Info(const Arguments& args, Context& ctx) {
  absl::StatusOr<pb::MapInfo> info = ctx.client->GetMapInfo();
  if (!info.ok()) return info.status();
  if (ctx.json) {
    *ctx.out << ToJson(*info);
    return absl::OkStatus();
  }
  *ctx.out << absl::StrFormat(
      "map version:       %d\nlandmarks:         %d\nfactors:           %d\nstrategy:          %s "
      "(warm-up %d passages, re-solved at each doubling up to %d, subgraph dim %d, "
      "window %d links%s, detections: %s)\n"
      "queue depth:       %d\npassages:          queued=%d processing=%d applied=%d rejected=%d failed=%d "
      "quarantined=%d discarded=%d\n"
      "re-linearisation:  %s\n",
      info->map_version(), info->landmark_count(), info->factor_count(), info->strategy(),
      info->warmup_passages(), info->relinearize_until_passages(), info->max_subgraph_dim(),
      info->window_hops(), info->window_hops() == 0 ? ": whole map" : "",
      !info->has_detections_per_landmark()    ? std::string("not reported by this server")
      : info->detections_per_landmark() == 0 ? std::string("all")
      : info->spread_detections()           ? absl::StrFormat("%d spread over each track", info->detections_per_landmark())
                                            : absl::StrFormat("the last %d", info->detections_per_landmark()),
      info->queue_depth(), info->passages_queued(), info->passages_processing(),
      info->passages_applied(), info->passages_rejected(), info->passages_failed(), info->passages_quarantined(),
      info->passages_discarded(),
      info->relinearize_sigmas() > 0.0
          ? absl::StrFormat("beyond %g sigmas, %d due (done while the queue is empty)", info->relinearize_sigmas(),
                            info->relinearizations_due())
          : std::string("off"));
  return absl::OkStatus();
}

// tile --at LAT,LON: the address of the storage (z16) tile containing the point; no call.
absl::Status TileAt(const Arguments& args, Context& ctx) {
  if (!args.positional.empty()) return UsageError("give either Z X Y or --at LAT,LON");
  const std::string& text = args.at;
  std::vector<std::string> parts = absl::StrSplit(text, ',');
  LatLon p;
  if (parts.size() != 2 || !absl::SimpleAtod(parts[0], &p.lat_deg) || !absl::SimpleAtod(parts[1], &p.lon_deg) ||
      !std::isfinite(p.lat_deg) || !std::isfinite(p.lon_deg)) {
    return UsageError(absl::StrCat("--at: '", text, "' is not LAT,LON (degrees)"));
  }
  if (std::abs(p.lat_deg) > kMaxMercatorLatDeg || std::abs(p.lon_deg) > 180) {
    return UsageError(absl::StrFormat("--at: need |LAT| <= %.4f (Web-Mercator) and |LON| <= 180, got %s", kMaxMercatorLatDeg,
                                      text));
  }
  const TileId tile = TileContaining(p, kStorageZoom);
  if (ctx.json) {
    *ctx.out << nlohmann::ordered_json{{"z", tile.z}, {"x", tile.x}, {"y", tile.y}}.dump(2) << "\n";
  } else {
    *ctx.out << absl::StrFormat("%d %d %d\n", tile.z, tile.x, tile.y);
  }
  return absl::OkStatus();
}

absl::Status Tile(const Arguments& args, Context& ctx) {
  if (!args.at.empty()) return TileAt(args, ctx);
  if (args.positional.size() != 3) return UsageError("give Z X Y or --at LAT,LON");
  int zxy[3];
  for (int i = 0; i < 3; ++i) {
    if (!absl::SimpleAtoi(args.positional[i], &zxy[i])) {
      return UsageError(absl::StrCat("'", args.positional[i], "' is not an integer"));
    }
  }
  absl::StatusOr<pb::GetTileResponse> tile = ctx.client->GetTile(zxy[0], zxy[1], zxy[2]);
  if (!tile.ok()) return tile.status();
  if (ctx.json) {
    *ctx.out << ToJson(*tile);
    return absl::OkStatus();
  }
  *ctx.out << absl::StrFormat("tile %d/%d/%d  tile version %d  map version %d  %d landmarks\n", zxy[0], zxy[1], zxy[2],
                              tile->tile_version(), tile->map_version(), tile->landmarks_size());
  PrintLandmarkTable({tile->landmarks().begin(), tile->landmarks().end()}, *ctx.out);
  return absl::OkStatus();
}

absl::Status Region(const Arguments& args, Context& ctx) {
  absl::StatusOr<pb::BoundingBox> box = ParseBbox(args, ctx);
  if (!box.ok()) return box.status();
  absl::StatusOr<RegionMap> region = ctx.client->QueryRegion(*box);
  if (!region.ok()) return region.status();
  if (ctx.json) {
    pb::QueryRegionResponse response;
    for (const pb::Landmark& l : region->landmarks) *response.add_landmarks() = l;
    response.set_map_version(region->map_version);
    *ctx.out << ToJson(response);
    return absl::OkStatus();
  }
  *ctx.out << absl::StrFormat("map version %d  %d landmarks\n", region->map_version, region->landmarks.size());
  PrintLandmarkTable(region->landmarks, *ctx.out);
  return absl::OkStatus();
}

absl::Status Watch(const Arguments& args, Context& ctx) {
  absl::StatusOr<pb::BoundingBox> box = ParseBbox(args, ctx);
  if (!box.ok()) return box.status();
  MapClient::WatchOptions options;
  if (args.seconds > 0) options.duration = std::chrono::milliseconds(static_cast<int64_t>(args.seconds * 1000));
  options.reconnect = true;
  options.on_reconnect = [&](const absl::Status& lost, int64_t version) {
    ctx.Warn() << "connection lost (" << absl::StatusCodeToString(lost.code()) << ": " << OneLine(lost.message())
               << "); reconnecting from map version " << version << "\n";
  };
  int64_t received = 0;
  return ctx.client->WatchRegion(*box, args.since, [&](const pb::WatchRegionResponse& change) {
    if (ctx.json) {
      std::string line;
      google::protobuf::util::JsonPrintOptions options;
      options.always_print_primitive_fields = true;
      (void)google::protobuf::util::MessageToJsonString(change, &line, options);
      *ctx.out << line << "\n";
    } else {
      *ctx.out << absl::StrFormat("map version %d: %d landmarks changed", change.map_version(),
                                  change.landmarks_size());
      if (change.removed_landmark_ids_size() > 0) {
        *ctx.out << absl::StrFormat(", %d removed", change.removed_landmark_ids_size());
      }
      *ctx.out << "\n";
      for (const pb::Landmark& l : change.landmarks()) {
        *ctx.out << absl::StrFormat("  landmark %d  %.8f %.8f  version %d  seen %d\n", l.id(), l.lat_deg(),
                                    l.lon_deg(), l.version(), l.passages_seen());
      }
      for (int64_t id : change.removed_landmark_ids()) *ctx.out << absl::StrFormat("  landmark %d  removed\n", id);
    }
    ctx.out->flush();
    return args.updates <= 0 || ++received < args.updates;
  }, options);
}

absl::Status WriteTextFile(const std::string& path, const std::string& text) {
  std::ofstream file(path, std::ios::trunc);
  file << text;
  file.close();
  if (!file) return absl::UnavailableError(absl::StrCat(path, ": write failed"));
  return absl::OkStatus();
}

absl::Status Export(const Arguments& args, Context& ctx) {
  absl::StatusOr<pb::BoundingBox> box = ParseBbox(args, ctx);
  if (!box.ok()) return box.status();
  absl::StatusOr<RegionMap> region = ctx.client->QueryRegion(*box);
  if (!region.ok()) return region.status();
  GeoJsonOptions options;
  options.ellipses = args.ellipses;
  const std::string text = LandmarksToGeoJson(region->landmarks, region->map_version, options);
  if (args.out.empty()) {
    *ctx.out << text;
    return absl::OkStatus();
  }
  if (absl::Status s = WriteTextFile(args.out, text); !s.ok()) return s;
  if (!ctx.json) *ctx.out << absl::StrFormat("wrote %d landmarks (map version %d) to %s\n", region->landmarks.size(), region->map_version, args.out);
  return absl::OkStatus();
}

absl::Status Localize(const Arguments& args, Context& ctx) {
  if (args.positional.size() != 1) return UsageError("give one passage file");
  absl::StatusOr<pb::Passage> passage = ReadPassageFile(args.positional[0]);
  if (!passage.ok()) return passage.status();
  absl::StatusOr<pb::LocalizePassageResponse> response = ctx.client->LocalizePassage(*passage);
  if (!response.ok()) return response.status();
  if (ctx.json) {
    *ctx.out << ToJson(*response);
    return absl::OkStatus();
  }
  const std::string text = args.format == "csv" ? LocalizationToCsv(*response) : LocalizationToGeoJson(*response);
  if (args.out.empty()) {
    *ctx.out << text;
    return absl::OkStatus();
  }
  if (absl::Status s = WriteTextFile(args.out, text); !s.ok()) return s;
  *ctx.out << absl::StrFormat(
      "wrote %d poses to %s (map version %d, %d landmarks used, %d detections rejected, chi2 %.1f / %d dof, "
      "camera yaw %+.2f° ± %.2f°)\n",
      response->poses_size(), args.out, response->map_version(), response->landmarks_used_size(),
      response->rejected_size(), response->chi2(), response->dof(), response->camera_yaw_estimate_rad() * kDeg,
      response->camera_yaw_estimate_sigma_rad() * kDeg);
  return absl::OkStatus();
}

using Command = absl::Status (*)(const Arguments&, Context&);

// --server, --json, --deadline-s and the TLS and token flags, which every command takes.
void AddCommonFlags(CLI::App* command, Arguments* args) {
  const std::string group = "Common flags";
  AddServerFlag(command, &args->server)->group(group);
  command->add_flag("--json", args->json,
                    "machine-readable output (protobuf JSON, zero-valued fields included) instead of tables")
      ->group(group);
  command->add_option("--deadline-s", args->deadline_s, "deadline of each call, seconds")
      ->check(Positive())
      ->group(group);
  AddClientSecurityFlags(command, &args->security);
}

// A command: what it runs, and its flags and arguments once parsed. Every command has its own,
// for CLI11 reads the environment ($MAPCTL_SERVER) into the flags of every command, parsed or not.
struct MapctlCommand {
  Command run = nullptr;
  Arguments args;
};

// mapctl's command line: `commands` gets each command by name, its flags bound.
std::unique_ptr<CLI::App> NewMapctlCommandLine(std::map<std::string, MapctlCommand>* commands) {
  std::unique_ptr<CLI::App> app = NewCommandLine(
      "mapctl", "mapctl: operate a crowdmap map service (mapd). `mapctl COMMAND --help` lists a command's flags.",
      kExitCodes);
  auto add = [&](const char* name, const char* description, Command run) {
    MapctlCommand& command = (*commands)[name];
    command.run = run;
    return std::make_pair(app->add_subcommand(name, description), &command.args);
  };
  auto add_passage_command = [&](const char* name, const char* description, Command run) {
    auto [command, args] = add(name, description, run);
    command->add_option("ID", args->positional, "server id, or VEHICLE/PASSAGE_ID");
  };
  auto add_bbox = [](CLI::App* command, Arguments* args) {
    command->add_option("--bbox", args->bbox,
                        "the box, degrees (a box valid only with lat and lon swapped is read swapped, with a\n"
                        "warning)")
        ->type_name("MINLON,MINLAT,MAXLON,MAXLAT")
        ->required();
  };
  auto add_out = [](CLI::App* command, Arguments* args) {
    command->add_option("--out", args->out, "write to FILE (default stdout)")->type_name("FILE");
  };

  auto [upload, upload_args] = add("upload", "upload passage files (protobuf JSON or binary mapservice.v1.Passage)", &Upload);
  upload->add_option("FILE", upload_args->positional,
                     "passage files; one the server refuses (invalid, a drive already uploaded) is reported\n"
                     "and the rest are still sent (exit code 1)");
  add_passage_command("status", "one passage", &Status);
  auto [passages, passages_args] = add("passages", "uploaded passages", &Passages);
  passages
      ->add_option("--state", passages_args->state,
                   "only those in state S: queued | processing | applied | rejected | failed | excluded |\n"
                   "quarantined | discarded")
      ->type_name("S");
  auto [landmark, landmark_args] = add("landmark", "one landmark and the passages that shaped it", &LandmarkCommand);
  landmark->add_option("ID", landmark_args->positional, "landmark id");
  add_passage_command("exclude",
                      "take an applied passage out of the map: the map becomes what it would be without it",
                      &Exclude);
  add_passage_command("requeue",
                      "put a failed or quarantined passage back in the queue (its attempts cleared; the map's\n"
                      "checks apply again)",
                      &Requeue);
  add_passage_command("release",
                      "queue a quarantined passage to be applied once with the map's consistency checks off\n"
                      "(you vouch for it, e.g. a landmark moved)",
                      &Release);
  add_passage_command("discard", "mark a failed or quarantined passage discarded: never applied", &Discard);
  add("info", "map version, landmark and queue counts, strategy", &Info);
  auto [tile, tile_args] =
      add("tile", "landmarks of one z16 tile, Z X Y; with --at, the tile containing a point (no call)", &Tile);
  tile->add_option("Z_X_Y", tile_args->positional, "the tile: zoom, column, row");
  tile->add_option("--at", tile_args->at, "print the z16 tile containing this point as Z X Y")->type_name("LAT,LON");
  auto [region, region_args] = add("region", "landmarks inside a bounding box", &Region);
  add_bbox(region, region_args);
  auto [watch, watch_args] = add("watch",
                                 "follow changes in a bounding box (until Ctrl-C, --seconds or --updates): the\n"
                                 "landmarks changed and those removed (\"landmark ID  removed\"); each\n"
                                 "call's first answer must come within --deadline-s; when the server restarts,\n"
                                 "it reconnects from the last version received (waiting up to --deadline-s for\n"
                                 "the server, a warning on stderr)",
                                 &Watch);
  add_bbox(watch, watch_args);
  watch->add_option("--since", watch_args->since, "start after this map version")
      ->check(NonNegative())
      ->type_name("V");
  watch->add_option("--seconds", watch_args->seconds, "stop after S seconds (0 = until Ctrl-C or --updates)")
      ->check(NonNegative())
      ->type_name("S");
  watch->add_option("--updates", watch_args->updates, "stop after N updates (0 = no limit)")->type_name("N");
  auto [export_command, export_args] =
      add("export", "RFC 7946 FeatureCollection of the landmarks in a bounding box", &Export);
  add_bbox(export_command, export_args);
  export_args->format = "geojson";
  export_command->add_option("--format", export_args->format, "output format")->check(CLI::IsMember({"geojson"}));
  export_command->add_flag("--ellipses", export_args->ellipses, "add each landmark's 95% error ellipse as a polygon");
  add_out(export_command, export_args);
  auto [localize, localize_args] = add("localize",
                                       "localise a passage file against the map (read-only): the pose at every node\n"
                                       "with its covariance",
                                       &Localize);
  localize->add_option("FILE", localize_args->positional, "passage file");
  localize_args->format = "csv";
  localize->add_option("--format", localize_args->format, "output format")->check(CLI::IsMember({"csv", "geojson"}));
  add_out(localize, localize_args);
  auto [vehicles, vehicles_args] = add("vehicles",
                                       "the camera yaw offset estimated for each vehicle (operators), or for one, e.g.\n"
                                       "\"camera yaw +0.52° ± 0.03° after 14 passages\"",
                                       &Vehicles);
  vehicles->add_option("ID", vehicles_args->positional, "vehicle id");
  for (auto& [name, command] : *commands) AddCommonFlags(app->get_subcommand(name), &command.args);
  return app;
}

// The client the common flags describe; errors are usage errors.
absl::StatusOr<std::unique_ptr<MapClient>> ClientFromFlags(const Arguments& args) {
  MapClientOptions options;
  options.server = args.server;
  options.call_deadline = std::chrono::milliseconds(static_cast<int64_t>(args.deadline_s * 1000));
  absl::StatusOr<ClientSecurityOptions> security = ClientSecurityFromFlags(args.security);
  if (!security.ok()) return security.status();
  options.security = *std::move(security);
  absl::StatusOr<std::unique_ptr<MapClient>> client = MapClient::Create(options);
  if (!client.ok()) return AsUsageError(client.status());
  return client;
}

}  // namespace

int RunMapctl(const std::vector<std::string>& args, std::ostream& out, std::ostream& err) {
  std::map<std::string, MapctlCommand> commands;
  std::unique_ptr<CLI::App> app = NewMapctlCommandLine(&commands);
  if (args.empty()) {
    err << app->help();
    return kExitUsage;
  }
  absl::StatusOr<ParsedCommandLine> parsed = ParseCommandLine(*app, args, out);
  if (parsed.ok() && *parsed == ParsedCommandLine::kPrintedHelpOrVersion) return kExitOk;
  const std::string name = ParsedCommand(*app);
  absl::Status status = parsed.status();
  if (status.ok()) {
    const MapctlCommand& command = commands.at(name);
    absl::StatusOr<std::unique_ptr<MapClient>> client = ClientFromFlags(command.args);
    status = client.status();
    if (client.ok()) {
      Context ctx{*std::move(client), command.args.json, &out, &err, name};
      status = command.run(command.args, ctx);
    }
  }
  const std::string where = name.empty() ? "mapctl" : absl::StrCat("mapctl ", name);
  if (IsUsageError(status)) {
    err << where << ": " << OneLine(status.message()) << " (see mapctl --help)\n";
  } else if (!status.ok()) {
    err << where << ": " << absl::StatusCodeToString(status.code()) << ": " << OneLine(status.message()) << "\n";
  }
  return ExitCodeFor(status);
}

}  // namespace crowdmap
