// Estimates a spinning LiDAR's beam elevation table from recorded scans (KITTI Velodyne .bin).
//
//   estimate_beam_table DIR_WITH_BIN_FILES [BEAMS=64]
//
// KITTI stores each scan laser by laser: every laser sweeps once around (azimuth turning one way)
// before the next one starts at the same azimuth. The azimuth is unwrapped along the file and each
// point's laser is floor(|unwrapped - start| / 2 pi); scans that do not hold exactly BEAMS turns
// (dropped sections) are skipped. A laser's elevation seen from the sensor origin depends on range
// for near points (each laser sits a few cm above or below the origin), so per laser only its
// farthest quarter of points (by horizontal distance) is used, and the table entry is their
// median elevation. The table is printed sorted from the highest beam down, as C++ constants
// (render/lidar/lidar_model.cc: kKittiHdl64eElevationDeg).
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

#include "scene/log/drive_log.h"

namespace {

double Median(std::vector<double> v) {
  if (v.empty()) return NAN;
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2) {
    std::fprintf(stderr, "usage: estimate_beam_table DIR_WITH_BIN_FILES [BEAMS=64]\n");
    return 2;
  }
  const int beams = argc > 2 ? std::atoi(argv[2]) : 64;
  std::vector<std::string> files;
  for (const auto& e : std::filesystem::directory_iterator(argv[1])) {
    if (e.path().extension() == ".bin") files.push_back(e.path().string());
  }
  std::sort(files.begin(), files.end());
  // Per laser: (horizontal distance, elevation in degrees) over all usable scans.
  std::vector<std::vector<std::pair<double, double>>> per_laser(beams);
  int used = 0;
  for (const std::string& f : files) {
    absl::StatusOr<streetsim::LidarScan> scan = streetsim::LoadLidarScan(f);
    if (!scan.ok()) {
      std::fprintf(stderr, "%s\n", std::string(scan.status().message()).c_str());
      return 1;
    }
    const auto& pts = scan->points;
    if (pts.empty()) continue;
    std::vector<int> laser(pts.size());
    double prev = 0, offset = 0, start = 0;
    for (size_t i = 0; i < pts.size(); ++i) {
      const double az = std::atan2(pts[i].y(), pts[i].x());
      if (i > 0) {
        if (az - prev > 3.0) offset -= 2 * M_PI;
        if (az - prev < -3.0) offset += 2 * M_PI;
      }
      prev = az;
      const double unwrapped = az + offset;
      if (i == 0) start = unwrapped;
      laser[i] = static_cast<int>(std::floor(std::fabs(unwrapped - start) / (2 * M_PI)));
    }
    if (laser.back() != beams - 1) continue;  // not exactly `beams` turns
    ++used;
    for (size_t i = 0; i < pts.size(); ++i) {
      const double rho = std::hypot(pts[i].x(), pts[i].y());
      if (rho < 1.0) continue;
      per_laser[laser[i]].push_back({rho, std::atan2(pts[i].z(), rho) * 180.0 / M_PI});
    }
  }
  std::vector<double> table;
  for (int b = 0; b < beams; ++b) {
    auto& v = per_laser[b];
    if (v.size() < 100) {
      std::fprintf(stderr, "laser %d has %zu points: not enough\n", b, v.size());
      return 1;
    }
    std::sort(v.begin(), v.end());
    std::vector<double> far;
    for (size_t i = v.size() * 3 / 4; i < v.size(); ++i) far.push_back(v[i].second);
    table.push_back(Median(far));
  }
  std::sort(table.begin(), table.end(), std::greater<double>());
  std::printf("// %d beams from %d of %zu scans in %s\n", beams, used, files.size(), argv[1]);
  std::printf("{");
  for (int b = 0; b < beams; ++b) std::printf("%s%.3f", b == 0 ? "" : (b % 8 == 0 ? ",\n " : ", "), table[b]);
  std::printf("}\n");
  return 0;
}
