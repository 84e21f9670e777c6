#include "scene/gaussians/synthetic_street.h"

#include <algorithm>
#include <cmath>
#include <random>

namespace streetsim {
namespace {

struct Sampler {
  std::mt19937_64 rng;
  double Uniform(double lo, double hi) { return std::uniform_real_distribution<double>(lo, hi)(rng); }
  double Normal(double sd) { return std::normal_distribution<double>(0.0, sd)(rng); }
  double LogUniform(double lo, double hi) { return std::exp(Uniform(std::log(lo), std::log(hi))); }
};

// Writes Gaussian i with a colour (linear RGB in [0,1]) turned into the SH DC coefficient, small
// random higher-order terms, and the given extents.
void Emit(GaussianStore* s, Sampler* r, size_t i, Eigen::Vector3d mean, Eigen::Vector3d scale,
          Eigen::Vector3d rgb, double opacity) {
  for (int k = 0; k < 3; ++k) {
    s->means[i * 3 + k] = static_cast<float>(mean[k]);
    s->log_scales[i * 3 + k] = static_cast<float>(std::log(std::max(scale[k], 1e-4)));
  }
  Eigen::Quaterniond q = Eigen::Quaterniond::UnitRandom();
  // Mostly axis-aligned surfaces with some jitter, as trained street scenes look.
  q = q.slerp(0.85, Eigen::Quaterniond::Identity());
  s->rotations[i * 4 + 0] = static_cast<float>(q.w());
  s->rotations[i * 4 + 1] = static_cast<float>(q.x());
  s->rotations[i * 4 + 2] = static_cast<float>(q.y());
  s->rotations[i * 4 + 3] = static_cast<float>(q.z());
  opacity = std::clamp(opacity, 0.005, 0.995);
  s->opacity_logits[i] = static_cast<float>(std::log(opacity / (1 - opacity)));
  const int K = s->sh_coeffs();
  float* sh = &s->sh[i * K * 3];
  constexpr double kC0 = 0.28209479177387814;
  for (int c = 0; c < 3; ++c) sh[c] = static_cast<float>((std::clamp(rgb[c], 0.0, 1.0) - 0.5) / kC0);
  for (int k = 1; k < K; ++k)
    for (int c = 0; c < 3; ++c) sh[k * 3 + c] = static_cast<float>(r->Normal(0.05));
}

}  // namespace

GaussianStore MakeSyntheticStreet(const SyntheticStreetOptions& o) {
  GaussianStore s;
  s.sh_degree = o.sh_degree;
  s.Resize(o.num_gaussians);
  Sampler r{std::mt19937_64(o.seed)};
  const double x0 = -30, x1 = x0 + o.street_length_m, hw = o.street_half_width_m;

  // Parked cars: boxes along both kerbs.
  struct Car { Eigen::Vector3d c; Eigen::Vector3d colour; };
  std::vector<Car> cars;
  for (double x = x0 + 5; x < x1 - 5; x += r.Uniform(6, 14)) {
    const double side = r.Uniform(0, 1) < 0.5 ? -1 : 1;
    cars.push_back({{x, side * (hw - 1.2), 0.75}, {r.Uniform(0, 1), r.Uniform(0, 1), r.Uniform(0, 1)}});
  }

  for (size_t i = 0; i < o.num_gaussians; ++i) {
    const double u = r.Uniform(0, 1);
    if (u < 0.30) {  // road and sidewalks: flat splats
      const double y = r.Uniform(-hw - 3, hw + 3);
      const double grey = std::abs(y) > hw ? 0.55 : 0.3 + r.Normal(0.04);
      const double sxy = r.LogUniform(0.05, 0.4);
      Emit(&s, &r, i, {r.Uniform(x0, x1), y, r.Normal(0.01) + (std::abs(y) > hw ? 0.15 : 0)},
           {sxy, sxy * r.Uniform(0.5, 1.5), sxy * 0.05}, {grey, grey, grey * 1.03},
           r.Uniform(0.3, 1.0));
    } else if (u < 0.60) {  // facades: thin in y
      const double side = r.Uniform(0, 1) < 0.5 ? -1 : 1;
      const double sxz = r.LogUniform(0.05, 0.6);
      const double tone = r.Uniform(0.3, 0.9);
      Emit(&s, &r, i, {r.Uniform(x0, x1), side * (hw + 3 + r.Uniform(0, 2)), r.Uniform(0, 15)},
           {sxz, sxz * 0.05, sxz * r.Uniform(0.5, 1.5)}, {tone, tone * 0.9, tone * 0.8},
           r.Uniform(0.2, 1.0));
    } else if (u < 0.75 && !cars.empty()) {  // cars
      const Car& car = cars[std::uniform_int_distribution<size_t>(0, cars.size() - 1)(r.rng)];
      const double sc = r.LogUniform(0.03, 0.25);
      Emit(&s, &r, i,
           car.c + Eigen::Vector3d(r.Uniform(-2.2, 2.2), r.Uniform(-0.9, 0.9), r.Uniform(-0.7, 0.7)),
           {sc, sc * r.Uniform(0.3, 1.0), sc * r.Uniform(0.3, 1.0)}, car.colour, r.Uniform(0.4, 1.0));
    } else if (u < 0.85) {  // poles and trees along the kerb
      const double x = std::floor(r.Uniform(x0, x1) / 12) * 12;
      const double side = r.Uniform(0, 1) < 0.5 ? -1 : 1;
      const double z = r.Uniform(0, 7);
      const bool crown = z > 3;
      const double spread = crown ? 1.5 : 0.1;
      const double sc = r.LogUniform(0.05, crown ? 0.5 : 0.15);
      Emit(&s, &r, i, {x + r.Normal(spread), side * (hw + 1) + r.Normal(spread), z},
           {sc, sc, sc * (crown ? 1.0 : 3.0)},
           crown ? Eigen::Vector3d(0.2, 0.45 + r.Normal(0.05), 0.15) : Eigen::Vector3d(0.4, 0.4, 0.4),
           r.Uniform(0.3, 1.0));
    } else if (u < 0.95) {  // clutter
      const double sc = r.LogUniform(0.02, 0.3);
      Emit(&s, &r, i, {r.Uniform(x0, x1), r.Uniform(-hw - 5, hw + 5), r.Uniform(0, 6)},
           {sc, sc * r.Uniform(0.3, 1), sc * r.Uniform(0.3, 1)},
           {r.Uniform(0, 1), r.Uniform(0, 1), r.Uniform(0, 1)}, r.Uniform(0.05, 0.8));
    } else {  // far sky shell: big, soft
      const double az = r.Uniform(-M_PI, M_PI), el = r.Uniform(0.02, 1.2);
      const double d = r.Uniform(200, 400);
      const double sc = r.LogUniform(5, 25);
      Emit(&s, &r, i, {d * std::cos(el) * std::cos(az), d * std::cos(el) * std::sin(az), d * std::sin(el)},
           {sc, sc, sc}, {0.55 + r.Normal(0.03), 0.7 + r.Normal(0.03), 0.9}, r.Uniform(0.3, 0.9));
    }
  }
  return s;
}

Eigen::Isometry3d StreetCameraPose(double x_m, double lateral_m) {
  Eigen::Matrix3d R;
  // Columns: camera x (right) = world -y, camera y (down) = world -z, camera z (forward) = world x.
  R << 0, 0, 1,  //
      -1, 0, 0,  //
      0, -1, 0;
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = R;
  T.translation() = Eigen::Vector3d(x_m, lateral_m, 1.65);
  return T;
}

}  // namespace streetsim
