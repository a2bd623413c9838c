#include "client/mapctl/mapctl.h"

#include <cmath>
#include <cstdlib>
#include <fstream>
#include <map>
#include <memory>
#include <optional>

#include <google/protobuf/util/json_util.h>

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
#include "client/common/flags.h"
#include "client/mapctl/table_cell.h"

namespace crowdmap {
namespace {

constexpr char kUsage[] = R"(mapctl: operate a crowdmap map service (mapd).

Usage: mapctl COMMAND [ARGS] [--server HOST:PORT] [--json] [--deadline-s S]
       mapctl --version

Commands:
  upload FILE...                 upload passage files (protobuf JSON or binary mapservice.v1.Passage)
  status ID                      one passage: server id, or VEHICLE/PASSAGE_ID
  passages [--state S]           uploaded passages; S = queued | processing | applied | rejected | failed
                                 | excluded | quarantined | discarded
  landmark ID                    one landmark and the passages that shaped it
  exclude ID                     take an applied passage out of the map (server id, or
                                 VEHICLE/PASSAGE_ID): the map becomes what it would be without it
  requeue ID                     put a failed or quarantined passage back in the queue (its
                                 attempts cleared; the map's checks apply again)
  release ID                     queue a quarantined passage to be applied once with the map's
                                 consistency checks off (you vouch for it, e.g. a landmark moved)
  discard ID                     mark a failed or quarantined passage discarded: never applied
  info                           map version, landmark and queue counts, strategy
  tile Z X Y                     landmarks of one z16 tile
  tile --at LAT,LON              the z16 tile containing a point, printed as Z X Y (no call)
  region --bbox MINLON,MINLAT,MAXLON,MAXLAT
                                 landmarks inside a bounding box (a box valid only with lat and
                                 lon swapped is read swapped, with a warning)
  watch --bbox ... [--since V] [--seconds S] [--updates N]
                                 follow changes in a bounding box (until Ctrl-C, S seconds or N updates);
                                 each call's first answer must come within --deadline-s; when the
                                 server restarts, it reconnects from the last version received
                                 (waiting up to --deadline-s for the server, a warning on stderr)
  export --bbox ... --format geojson [--ellipses] [--out FILE]
                                 RFC 7946 FeatureCollection of the landmarks (stdout unless --out)
  localize FILE [--format csv|geojson] [--out FILE]
                                 localise a passage file against the map (read-only): the pose at
                                 every node with its covariance (CSV by default; stdout unless --out)
  vehicles [ID]                  the camera yaw offset estimated for each vehicle (operators), or
                                 for one, e.g. "camera yaw +0.52° ± 0.03° after 14 passages"

Common flags:
  --server HOST:PORT             mapd address (default $MAPCTL_SERVER or 127.0.0.1:50051)
  --json                         machine-readable output (protobuf JSON, zero-valued fields
                                 included) instead of tables
  --deadline-s S                 deadline of each call, seconds (default 10)
  --tls-ca PATH                  TLS: the PEM CA that signed mapd's certificate (default plaintext)
  --tls-cert PATH --tls-key PATH mTLS: this client's PEM certificate and key
  --tls-server-name NAME         the name in mapd's certificate, if not the --server host
  --token-file PATH              bearer token (default $CROWDMAP_TOKEN_FILE; none)

Exit codes: 0 success, 1 failure (unreachable server, malformed file, unknown id, ...), 2 usage error
(unknown command or flag, missing argument, bad value), reported before any call is made.
)";

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
absl::StatusOr<pb::BoundingBox> ParseBbox(const Flags& flags, Context& ctx) {
  if (!flags.Has("bbox")) return UsageError("--bbox MINLON,MINLAT,MAXLON,MAXLAT is required");
  const std::string text = flags.GetString("bbox", "");
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

absl::Status Upload(const Flags& flags, Context& ctx) {
  if (flags.positional().empty()) return UsageError("give at least one passage file");
  std::vector<std::pair<std::string, pb::Passage>> files;
  for (const std::string& path : flags.positional()) {
    absl::StatusOr<pb::Passage> passage = ReadPassageFile(path);
    if (!passage.ok()) return passage.status();
    files.emplace_back(path, *std::move(passage));
  }
  if (!ctx.json) *ctx.out << absl::StrFormat("%-32s %8s  %-14s %-16s %-10s %s\n", "FILE", "ID", "VEHICLE", "PASSAGE", "STATE", "DUPLICATE");
  for (const auto& [path, passage] : files) {
    absl::StatusOr<pb::UploadPassageResponse> response = ctx.client->Upload(passage);
    if (!response.ok()) return absl::Status(response.status().code(), absl::StrCat(path, ": ", response.status().message()));
    if (ctx.json) {
      *ctx.out << ToJson(*response);
    } else {
      const pb::PassageStatus& s = response->status();
      *ctx.out << absl::StrFormat("%s %8d  %s %s %-10s %s\n", TableCell(path, 32), s.id(), TableCell(s.vehicle_id(), 14),
                                  TableCell(s.passage_id(), 16), StateName(s.state()),
                                  response->duplicate() ? "yes" : "no");
    }
  }
  return absl::OkStatus();
}

// The passage named by a command's one argument: a server id, or VEHICLE/PASSAGE_ID.
absl::StatusOr<PassageKey> PassageArgument(const Flags& flags) {
  if (flags.positional().size() != 1) {
    return UsageError(absl::StrCat("give one ID (number or VEHICLE/PASSAGE_ID)"));
  }
  const std::string& arg = flags.positional()[0];
  PassageKey key;
  if (absl::SimpleAtoi(arg, &key.id)) return key;
  if (size_t slash = arg.find('/'); slash != std::string::npos) {
    key.vehicle_id = arg.substr(0, slash);
    key.passage_id = arg.substr(slash + 1);
    return key;
  }
  return UsageError(absl::StrCat("'", arg, "' is neither a number nor VEHICLE/PASSAGE_ID"));
}

absl::Status Status(const Flags& flags, Context& ctx) {
  absl::StatusOr<PassageKey> key = PassageArgument(flags);
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

absl::Status LandmarkCommand(const Flags& flags, Context& ctx) {
  int64_t id = 0;
  if (flags.positional().size() != 1 || !absl::SimpleAtoi(flags.positional()[0], &id)) {
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

// "camera yaw +0.52° ± 0.03° after 14 passages"
std::string DescribeVehicleYaw(const pb::Vehicle& v) {
  constexpr double kDeg = 180.0 / M_PI;
  return absl::StrFormat("camera yaw %+.2f° ± %.2f° after %d passage%s", v.camera_yaw_offset_rad() * kDeg,
                         v.camera_yaw_sigma_rad() * kDeg, v.passages(), v.passages() == 1 ? "" : "s");
}

absl::Status Vehicles(const Flags& flags, Context& ctx) {
  if (flags.positional().size() > 1) return UsageError("give at most one vehicle id");
  if (flags.positional().size() == 1) {
    absl::StatusOr<pb::Vehicle> vehicle = ctx.client->GetVehicle(flags.positional()[0]);
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

absl::Status Exclude(const Flags& flags, Context& ctx) {
  absl::StatusOr<PassageKey> key = PassageArgument(flags);
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
absl::Status Resolve(pb::ResolvePassageRequest::Action action, const Flags& flags, Context& ctx) {
  absl::StatusOr<PassageKey> key = PassageArgument(flags);
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

absl::Status Requeue(const Flags& flags, Context& ctx) {
  return Resolve(pb::ResolvePassageRequest::REQUEUE, flags, ctx);
}

absl::Status Release(const Flags& flags, Context& ctx) {
  return Resolve(pb::ResolvePassageRequest::RELEASE, flags, ctx);
}

absl::Status Discard(const Flags& flags, Context& ctx) {
  return Resolve(pb::ResolvePassageRequest::DISCARD, flags, ctx);
}

absl::Status Passages(const Flags& flags, Context& ctx) {
  std::optional<pb::PassageState> state;
  if (flags.Has("state")) {
    absl::StatusOr<pb::PassageState> s = ParseState(flags.GetString("state", ""));
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

absl::Status Info(const Flags& flags, Context& ctx) {
  absl::StatusOr<pb::MapInfo> info = ctx.client->GetMapInfo();
  if (!info.ok()) return info.status();
  if (ctx.json) {
    *ctx.out << ToJson(*info);
    return absl::OkStatus();
  }
  *ctx.out << absl::StrFormat(
      "map version:       %d\nlandmarks:         %d\nfactors:           %d\nstrategy:          %s "
      "(warm-up %d passages, re-solved at each doubling up to %d, subgraph dim %d, "
      "window %d links%s)\n"
      "queue depth:       %d\npassages:          queued=%d processing=%d applied=%d rejected=%d failed=%d "
      "quarantined=%d discarded=%d\n",
      info->map_version(), info->landmark_count(), info->factor_count(), info->strategy(),
      info->warmup_passages(), info->relinearize_until_passages(), info->max_subgraph_dim(),
      info->window_hops(), info->window_hops() == 0 ? ": whole map" : "", info->queue_depth(), info->passages_queued(), info->passages_processing(),
      info->passages_applied(), info->passages_rejected(), info->passages_failed(), info->passages_quarantined(),
      info->passages_discarded());
  return absl::OkStatus();
}

// tile --at LAT,LON: the address of the storage (z16) tile containing the point; no call.
absl::Status TileAt(const Flags& flags, Context& ctx) {
  if (!flags.positional().empty()) return UsageError("give either Z X Y or --at LAT,LON");
  const std::string text = flags.GetString("at", "");
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
    *ctx.out << absl::StrFormat("{\n  \"z\": %d,\n  \"x\": %d,\n  \"y\": %d\n}\n", tile.z, tile.x, tile.y);
  } else {
    *ctx.out << absl::StrFormat("%d %d %d\n", tile.z, tile.x, tile.y);
  }
  return absl::OkStatus();
}

absl::Status Tile(const Flags& flags, Context& ctx) {
  if (flags.Has("at")) return TileAt(flags, ctx);
  if (flags.positional().size() != 3) return UsageError("give Z X Y or --at LAT,LON");
  int zxy[3];
  for (int i = 0; i < 3; ++i) {
    if (!absl::SimpleAtoi(flags.positional()[i], &zxy[i])) {
      return UsageError(absl::StrCat("'", flags.positional()[i], "' is not an integer"));
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

absl::Status Region(const Flags& flags, Context& ctx) {
  absl::StatusOr<pb::BoundingBox> box = ParseBbox(flags, ctx);
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

absl::Status Watch(const Flags& flags, Context& ctx) {
  absl::StatusOr<pb::BoundingBox> box = ParseBbox(flags, ctx);
  if (!box.ok()) return box.status();
  absl::StatusOr<long long> since = flags.GetInt("since", 0), updates = flags.GetInt("updates", 0);
  absl::StatusOr<double> seconds = flags.GetDouble("seconds", 0.0);
  for (const absl::Status& s : {since.status(), updates.status(), seconds.status()}) {
    if (!s.ok()) return s;
  }
  if (*since < 0) return UsageError("--since: must be >= 0");
  if (!(*seconds >= 0)) return UsageError("--seconds: must be >= 0 (0 = until Ctrl-C or --updates)");
  MapClient::WatchOptions options;
  if (*seconds > 0) options.duration = std::chrono::milliseconds(static_cast<int64_t>(*seconds * 1000));
  options.reconnect = true;
  options.on_reconnect = [&](const absl::Status& lost, int64_t version) {
    ctx.Warn() << "connection lost (" << absl::StatusCodeToString(lost.code()) << ": " << OneLine(lost.message())
               << "); reconnecting from map version " << version << "\n";
  };
  long long received = 0;
  return ctx.client->WatchRegion(*box, *since, [&](const pb::WatchRegionResponse& change) {
    if (ctx.json) {
      std::string line;
      google::protobuf::util::JsonPrintOptions options;
      options.always_print_primitive_fields = true;
      (void)google::protobuf::util::MessageToJsonString(change, &line, options);
      *ctx.out << line << "\n";
    } else {
      *ctx.out << absl::StrFormat("map version %d: %d landmarks changed\n", change.map_version(),
                                  change.landmarks_size());
      for (const pb::Landmark& l : change.landmarks()) {
        *ctx.out << absl::StrFormat("  landmark %d  %.8f %.8f  version %d  seen %d\n", l.id(), l.lat_deg(),
                                    l.lon_deg(), l.version(), l.passages_seen());
      }
    }
    ctx.out->flush();
    return *updates <= 0 || ++received < *updates;
  }, options);
}

absl::Status WriteTextFile(const std::string& path, const std::string& text) {
  std::ofstream file(path, std::ios::trunc);
  file << text;
  file.close();
  if (!file) return absl::UnavailableError(absl::StrCat(path, ": write failed"));
  return absl::OkStatus();
}

absl::Status Export(const Flags& flags, Context& ctx) {
  absl::StatusOr<pb::BoundingBox> box = ParseBbox(flags, ctx);
  if (!box.ok()) return box.status();
  const std::string format = flags.GetString("format", "geojson");
  if (format != "geojson") return UsageError(absl::StrCat("--format: '", format, "' is not geojson"));
  absl::StatusOr<RegionMap> region = ctx.client->QueryRegion(*box);
  if (!region.ok()) return region.status();
  GeoJsonOptions options;
  options.ellipses = flags.Has("ellipses");
  const std::string text = LandmarksToGeoJson(region->landmarks, region->map_version, options);
  if (!flags.Has("out")) {
    *ctx.out << text;
    return absl::OkStatus();
  }
  const std::string path = flags.GetString("out", "");
  if (absl::Status s = WriteTextFile(path, text); !s.ok()) return s;
  if (!ctx.json) *ctx.out << absl::StrFormat("wrote %d landmarks (map version %d) to %s\n", region->landmarks.size(), region->map_version, path);
  return absl::OkStatus();
}

absl::Status Localize(const Flags& flags, Context& ctx) {
  if (flags.positional().size() != 1) return UsageError("give one passage file");
  const std::string format = flags.GetString("format", "csv");
  if (format != "csv" && format != "geojson") {
    return UsageError(absl::StrCat("--format: '", format, "' is not csv or geojson"));
  }
  absl::StatusOr<pb::Passage> passage = ReadPassageFile(flags.positional()[0]);
  if (!passage.ok()) return passage.status();
  absl::StatusOr<pb::LocalizePassageResponse> response = ctx.client->LocalizePassage(*passage);
  if (!response.ok()) return response.status();
  if (ctx.json) {
    *ctx.out << ToJson(*response);
    return absl::OkStatus();
  }
  const std::string text = format == "csv" ? LocalizationToCsv(*response) : LocalizationToGeoJson(*response);
  if (!flags.Has("out")) {
    *ctx.out << text;
    return absl::OkStatus();
  }
  const std::string path = flags.GetString("out", "");
  if (absl::Status s = WriteTextFile(path, text); !s.ok()) return s;
  *ctx.out << absl::StrFormat(
      "wrote %d poses to %s (map version %d, %d landmarks used, %d detections rejected, chi2 %.1f / %d dof)\n",
      response->poses_size(), path, response->map_version(), response->landmarks_used_size(),
      response->rejected_size(), response->chi2(), response->dof());
  return absl::OkStatus();
}

using Command = absl::Status (*)(const Flags&, Context&);

struct CommandSpec {
  Command run;
  std::map<std::string, bool> flags;  // besides the common ones
  bool no_arguments = false;          // takes flags only
};

const std::map<std::string, CommandSpec>& Commands() {
  static const auto* commands = new std::map<std::string, CommandSpec>{
      {"upload", {&Upload, {}}},
      {"status", {&Status, {}}},
      {"exclude", {&Exclude, {}}},
      {"requeue", {&Requeue, {}}},
      {"release", {&Release, {}}},
      {"discard", {&Discard, {}}},
      {"landmark", {&LandmarkCommand, {}}},
      {"passages", {&Passages, {{"state", true}}, true}},
      {"info", {&Info, {}, true}},
      {"tile", {&Tile, {{"at", true}}}},
      {"region", {&Region, {{"bbox", true}}, true}},
      {"watch", {&Watch, {{"bbox", true}, {"since", true}, {"seconds", true}, {"updates", true}}, true}},
      {"export", {&Export, {{"bbox", true}, {"format", true}, {"ellipses", false}, {"out", true}}, true}},
      {"localize", {&Localize, {{"format", true}, {"out", true}}}},
      {"vehicles", {&Vehicles, {}}},
  };
  return *commands;
}

}  // namespace

const char* MapctlUsage() { return kUsage; }

int RunMapctl(const std::vector<std::string>& args, std::ostream& out, std::ostream& err) {
  if (args.empty()) {
    err << kUsage;
    return kExitUsage;
  }
  if (args[0] == "--version") {
    out << "mapctl (crowdmap) " << CROWDMAP_VERSION << "\n";
    return kExitOk;
  }
  if (args[0] == "--help" || args[0] == "-h" || args[0] == "help") {
    out << kUsage;
    return kExitOk;
  }
  const std::string& name = args[0];
  auto it = Commands().find(name);
  if (it == Commands().end()) {
    err << "mapctl: unknown command '" << name << "' (see mapctl --help)\n";
    return kExitUsage;
  }
  std::map<std::string, bool> known = it->second.flags;
  known.insert({{"server", true}, {"json", false}, {"deadline-s", true}, {"help", false}});
  for (const auto& flag : ClientSecurityFlags()) known.insert(flag);
  absl::StatusOr<Flags> flags = Flags::Parse({args.begin() + 1, args.end()}, known);
  if (!flags.ok()) {
    err << "mapctl " << name << ": " << OneLine(flags.status().message()) << " (see mapctl --help)\n";
    return kExitUsage;
  }
  if (flags->Has("help")) {
    out << kUsage;
    return kExitOk;
  }
  if (it->second.no_arguments && !flags->positional().empty()) {
    err << "mapctl " << name << ": unexpected argument '" << flags->positional()[0] << "' (see mapctl --help)\n";
    return kExitUsage;
  }
  MapClientOptions options;
  const char* env_server = std::getenv("MAPCTL_SERVER");
  options.server = flags->GetString("server", env_server && *env_server ? env_server : options.server);
  absl::StatusOr<double> deadline_s = flags->GetDouble("deadline-s", 10.0);
  if (!deadline_s.ok() || !(*deadline_s > 0)) {
    err << "mapctl " << name << ": --deadline-s: need a positive number of seconds\n";
    return kExitUsage;
  }
  options.call_deadline = std::chrono::milliseconds(static_cast<int64_t>(*deadline_s * 1000));
  if (absl::Status s = ApplyClientSecurityFlags(*flags, &options.security); !s.ok()) {
    err << "mapctl " << name << ": " << OneLine(s.message()) << "\n";
    return kExitUsage;
  }
  absl::StatusOr<std::unique_ptr<MapClient>> client = MapClient::Create(options);
  if (!client.ok()) {
    err << "mapctl " << name << ": " << OneLine(client.status().message()) << "\n";
    return kExitUsage;
  }
  Context ctx{*std::move(client), flags->Has("json"), &out, &err, name};
  const absl::Status status = it->second.run(*flags, ctx);
  if (IsUsageError(status)) {
    err << "mapctl " << name << ": " << OneLine(status.message()) << " (see mapctl --help)\n";
  } else if (!status.ok()) {
    err << "mapctl " << name << ": " << absl::StatusCodeToString(status.code()) << ": "
        << OneLine(status.message()) << "\n";
  }
  return ExitCodeFor(status);
}

}  // namespace crowdmap
