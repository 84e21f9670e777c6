#include "render/lidar/lidar_model.h"

#include <cmath>

#include "absl/strings/str_cat.h"

namespace streetsim {
namespace {

constexpr double kDegToRad = M_PI / 180.0;

// HDL-64E beam elevations (degrees from the sensor origin, highest first), estimated from the 77
// complete scans of ../shared/data/kitti_raw/2011_09_26/2011_09_26_drive_sfnd_sync by
//   ninja -C build estimate_beam_table && build/tests/lidar/estimate_beam_table
//     ../shared/data/kitti_raw/2011_09_26/2011_09_26_drive_sfnd_sync/velodyne_points/data
// (one command line)
// (tests/lidar/estimate_beam_table.cc: lasers from the scan's point order, per laser the median
// elevation of its farthest quarter of points). The spec's +2.0 .. -24.8 is the lasers' own
// pointing; seen from the origin the bottom beams sit at -23.6 because each laser is mounted a few
// cm off the origin. tests/lidar/lidar_model_test.cc re-runs the estimate and compares.
constexpr double kKittiHdl64eElevationDeg[64] = {
    2.197,   1.843,   1.589,   1.164,   0.882,   0.482,   0.214,   -0.150,
    -0.488,  -0.883,  -1.177,  -1.516,  -1.881,  -2.212,  -2.532,  -2.887,
    -3.183,  -3.567,  -3.836,  -4.196,  -4.507,  -4.830,  -5.128,  -5.412,
    -5.750,  -6.024,  -6.302,  -6.558,  -6.917,  -7.281,  -7.513,  -7.899,
    -8.467,  -8.983,  -9.444,  -9.832,  -10.287, -10.884, -11.379, -11.799,
    -12.250, -12.670, -13.194, -13.707, -14.275, -14.714, -15.207, -15.570,
    -16.179, -16.694, -17.259, -17.711, -18.209, -18.596, -19.059, -19.601,
    -20.110, -20.704, -21.192, -21.584, -22.029, -22.651, -23.173, -23.645};

}  // namespace

absl::Status LidarModel::Validate() const {
  if (beams() < 2) return absl::InvalidArgumentError("LiDAR model needs at least 2 beams");
  for (int b = 0; b < beams(); ++b) {
    const double e = beam_elevation_deg[b];
    if (!std::isfinite(e) || e <= -90 || e >= 90) {
      return absl::InvalidArgumentError(absl::StrCat("beam ", b, " elevation ", e, " is not within (-90, 90) degrees"));
    }
    if (b > 0 && !(e < beam_elevation_deg[b - 1])) {
      return absl::InvalidArgumentError("beam elevations must be strictly decreasing (beam 0 highest)");
    }
  }
  if (columns < 1 || columns > 65536) return absl::InvalidArgumentError("LiDAR columns must be in 1..65536");
  if (!std::isfinite(min_range_m) || !std::isfinite(max_range_m) || min_range_m < 0 ||
      !(max_range_m > min_range_m)) {
    return absl::InvalidArgumentError("LiDAR range limits must satisfy 0 <= min < max (finite)");
  }
  if (sweep_duration_us < 0) return absl::InvalidArgumentError("sweep duration must be >= 0");
  const Eigen::Matrix3d R = T_ego_from_lidar.linear();
  if (!T_ego_from_lidar.matrix().allFinite() ||
      !(R.transpose() * R).isApprox(Eigen::Matrix3d::Identity(), 1e-6) || R.determinant() < 0) {
    return absl::InvalidArgumentError("T_ego_from_lidar must be a finite rigid transform");
  }
  return absl::OkStatus();
}

double LidarModel::BeamCoordinate(double elevation_rad, double* d_beam_d_elevation) const {
  const double e = elevation_rad / kDegToRad;
  const std::vector<double>& t = beam_elevation_deg;
  const int n = beams();
  // Segment [k, k+1] with t[k] >= e >= t[k+1]; the end segments extrapolate.
  int k;
  if (e >= t[0]) {
    k = 0;
  } else if (e <= t[n - 1]) {
    k = n - 2;
  } else {
    int lo = 0, hi = n - 1;  // t[lo] > e >= t[hi]
    while (hi - lo > 1) {
      const int mid = (lo + hi) / 2;
      if (t[mid] > e) lo = mid; else hi = mid;
    }
    k = lo;
  }
  const double slope = 1.0 / (t[k + 1] - t[k]);  // beams per degree (negative)
  if (d_beam_d_elevation) *d_beam_d_elevation = slope / kDegToRad;
  return k + (e - t[k]) * slope;
}

double LidarModel::BeamElevationRad(int b) const { return beam_elevation_deg[b] * kDegToRad; }

double LidarModel::ColumnCoordinate(double azimuth_rad) const {
  double u = (M_PI - azimuth_rad) * columns / (2 * M_PI) - 0.5;
  u = std::fmod(u + 0.5, static_cast<double>(columns));
  if (u < 0) u += columns;
  return u - 0.5;
}

double LidarModel::ColumnAzimuthRad(int c) const { return M_PI - (c + 0.5) * 2 * M_PI / columns; }

Eigen::Vector3d LidarModel::RayDirection(int beam, int column) const {
  const double el = BeamElevationRad(beam), az = ColumnAzimuthRad(column);
  return {std::cos(el) * std::cos(az), std::cos(el) * std::sin(az), std::sin(el)};
}

int64_t LidarModel::ColumnTimeOffsetUs(int column) const {
  return static_cast<int64_t>(std::llround((column + 0.5) * static_cast<double>(sweep_duration_us) / columns));
}

LidarModel KittiHdl64e(int columns) {
  LidarModel m;
  m.name = "kitti_hdl64e";
  m.beam_elevation_deg.assign(std::begin(kKittiHdl64eElevationDeg), std::end(kKittiHdl64eElevationDeg));
  m.columns = columns;
  return m;
}

}  // namespace streetsim
