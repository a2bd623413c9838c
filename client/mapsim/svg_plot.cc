#include "client/mapsim/svg_plot.h"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <functional>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

namespace crowdmap {
namespace {

constexpr double kWidth = 900, kPanelHeight = 300, kLeft = 70, kRight = 20, kTop = 40, kGap = 70;

// Maps data to pixels inside one panel.
struct Axes {
  double x0, x1, y0, y1;  // data range
  double top;             // panel top in pixels
  bool log_y = false;
  double X(double x) const { return kLeft + (x - x0) / (x1 - x0) * (kWidth - kLeft - kRight); }
  double Y(double y) const {
    const double v = log_y ? std::log10(std::max(y, 1e-6)) : y;
    const double a = log_y ? std::log10(y0) : y0, b = log_y ? std::log10(y1) : y1;
    return top + kPanelHeight - (v - a) / (b - a) * kPanelHeight;
  }
};

std::string Polyline(const std::vector<PassageRecord>& r, const Axes& ax, const std::function<double(const PassageRecord&)>& f,
                     const std::string& style) {
  std::string points;
  for (const PassageRecord& p : r) {
    const double v = f(p);
    if (std::isfinite(v)) absl::StrAppendFormat(&points, "%.1f,%.1f ", ax.X(p.passage), ax.Y(v));
  }
  return absl::StrFormat("<polyline fill=\"none\" %s points=\"%s\"/>\n", style, points);
}

std::string Band(const std::vector<PassageRecord>& r, const Axes& ax, const std::function<double(const PassageRecord&)>& mid,
                 const std::function<double(const PassageRecord&)>& half, const std::string& fill) {
  std::string points;
  for (const PassageRecord& p : r) absl::StrAppendFormat(&points, "%.1f,%.1f ", ax.X(p.passage), ax.Y(mid(p) + half(p)));
  for (auto it = r.rbegin(); it != r.rend(); ++it) {
    absl::StrAppendFormat(&points, "%.1f,%.1f ", ax.X(it->passage), ax.Y(mid(*it) - half(*it)));
  }
  return absl::StrFormat("<polygon fill=\"%s\" fill-opacity=\"0.25\" stroke=\"none\" points=\"%s\"/>\n", fill, points);
}

std::string Frame(const Axes& ax, const std::string& ylabel, const std::vector<double>& yticks) {
  std::string s = absl::StrFormat("<rect x=\"%.1f\" y=\"%.1f\" width=\"%.1f\" height=\"%.1f\" fill=\"none\" stroke=\"#333\"/>\n",
                                  kLeft, ax.top, kWidth - kLeft - kRight, kPanelHeight);
  for (double y : yticks) {
    absl::StrAppendFormat(&s, "<line x1=\"%.1f\" x2=\"%.1f\" y1=\"%.1f\" y2=\"%.1f\" stroke=\"#ddd\"/>\n", kLeft,
                          kWidth - kRight, ax.Y(y), ax.Y(y));
    absl::StrAppendFormat(&s, "<text x=\"%.1f\" y=\"%.1f\" font-size=\"11\" text-anchor=\"end\">%g</text>\n", kLeft - 5,
                          ax.Y(y) + 4, y);
  }
  const int step = std::max(1, static_cast<int>(std::pow(10, std::floor(std::log10(std::max(1.0, ax.x1 - ax.x0))))));
  for (int x = 0; x <= ax.x1; x += step) {
    if (x < ax.x0) continue;
    absl::StrAppendFormat(&s, "<text x=\"%.1f\" y=\"%.1f\" font-size=\"11\" text-anchor=\"middle\">%d</text>\n", ax.X(x),
                          ax.top + kPanelHeight + 15, x);
  }
  absl::StrAppendFormat(&s, "<text x=\"15\" y=\"%.1f\" font-size=\"12\" transform=\"rotate(-90 15 %.1f)\" text-anchor=\"middle\">%s</text>\n",
                        ax.top + kPanelHeight / 2, ax.top + kPanelHeight / 2, ylabel);
  absl::StrAppendFormat(&s, "<text x=\"%.1f\" y=\"%.1f\" font-size=\"12\" text-anchor=\"middle\">passages</text>\n",
                        kLeft + (kWidth - kLeft - kRight) / 2, ax.top + kPanelHeight + 32);
  return s;
}

}  // namespace

absl::Status WriteErrorPlot(const std::vector<PassageRecord>& records, const std::string& title, const std::string& path) {
  if (records.empty()) return absl::InvalidArgumentError("no passages to plot");
  const double x0 = 1, x1 = std::max<double>(2, records.back().passage);
  double dmin = 1e9, dmax = 1e-9, band = 0.0;
  for (const PassageRecord& r : records) {
    const MapErrorMetrics& m = r.metrics;
    if (std::isfinite(m.mean_dist_err_m) && m.mean_dist_err_m > 0) {
      dmin = std::min(dmin, m.mean_dist_err_m);
      dmax = std::max(dmax, m.mean_dist_err_m);
    }
    // The East/North panel is scaled to the bands after the first tenth of the run.
    if (static_cast<size_t>(r.passage) > records.size() / 10) {
      for (double v : {std::abs(m.mean_east_err_m) + m.east_3sigma_m, std::abs(m.mean_north_err_m) + m.north_3sigma_m}) {
        if (std::isfinite(v)) band = std::max(band, v);
      }
    }
  }
  if (dmin > dmax) dmin = 0.01, dmax = 10;
  Axes dist{x0, x1, std::pow(10, std::floor(std::log10(dmin))), std::pow(10, std::ceil(std::log10(dmax))), kTop, true};
  const double en = band > 0 ? band * 1.1 : 1.0;
  Axes east{x0, x1, -en, en, kTop + kPanelHeight + kGap};
  Axes north{x0, x1, -en, en, kTop + 2 * (kPanelHeight + kGap)};

  std::vector<double> log_ticks;
  for (double t = dist.y0; t <= dist.y1 * 1.0001; t *= 10) log_ticks.push_back(t);
  const double tick = std::pow(10, std::floor(std::log10(en)));
  std::vector<double> en_ticks;
  for (double t = -std::floor(en / tick) * tick; t <= en; t += tick) en_ticks.push_back(std::abs(t) < 1e-12 ? 0 : t);

  std::string svg = absl::StrFormat(
      "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"%d\" height=\"%d\" font-family=\"sans-serif\">\n"
      "<rect width=\"100%%\" height=\"100%%\" fill=\"white\"/>\n"
      "<text x=\"%.1f\" y=\"22\" font-size=\"15\" text-anchor=\"middle\">%s</text>\n",
      static_cast<int>(kWidth), static_cast<int>(kTop + 3 * (kPanelHeight + kGap)), kWidth / 2, title);
  svg += Frame(dist, "mean distance error (m)", log_ticks);
  svg += Polyline(records, dist, [](const PassageRecord& r) { return r.metrics.mean_dist_err_m; },
                  "stroke=\"#1f77b4\" stroke-width=\"1.5\"");
  svg += Frame(east, "mean East error (m), +-3 sigma", en_ticks);
  svg += Band(records, east, [](const PassageRecord& r) { return r.metrics.mean_east_err_m; },
              [](const PassageRecord& r) { return r.metrics.east_3sigma_m; }, "#2ca02c");
  svg += Polyline(records, east, [](const PassageRecord& r) { return r.metrics.mean_east_err_m; },
                  "stroke=\"#2ca02c\" stroke-width=\"1.2\"");
  svg += Frame(north, "mean North error (m), +-3 sigma", en_ticks);
  svg += Band(records, north, [](const PassageRecord& r) { return r.metrics.mean_north_err_m; },
              [](const PassageRecord& r) { return r.metrics.north_3sigma_m; }, "#d62728");
  svg += Polyline(records, north, [](const PassageRecord& r) { return r.metrics.mean_north_err_m; },
                  "stroke=\"#d62728\" stroke-width=\"1.2\"");
  svg += "</svg>\n";

  std::ofstream out(path);
  out << svg;
  if (!out) return absl::InternalError(absl::StrCat("cannot write ", path));
  return absl::OkStatus();
}

}  // namespace crowdmap
