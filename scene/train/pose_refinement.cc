#include "scene/train/pose_refinement.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>

#include <Eigen/Geometry>
#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "scene/common/checked_file.h"

namespace streetsim::train {
namespace {

Eigen::Matrix3d RotationOf(const PoseDelta& d) {
  const Eigen::Vector3d w(d[0], d[1], d[2]);
  const double angle = w.norm();
  if (angle < 1e-12) return Eigen::Matrix3d::Identity();
  return Eigen::AngleAxisd(angle, w / angle).toRotationMatrix();
}

// SO(3)'s right Jacobian: R(w + dw) = R(w) Exp(J_r(w) dw) to first order.
Eigen::Matrix3d RightJacobian(const PoseDelta& d) {
  const Eigen::Vector3d w(d[0], d[1], d[2]);
  const double t = w.norm();
  Eigen::Matrix3d W;
  W << 0, -w.z(), w.y(), w.z(), 0, -w.x(), -w.y(), w.x(), 0;
  if (t < 1e-6) return Eigen::Matrix3d::Identity() - 0.5 * W;
  return Eigen::Matrix3d::Identity() - (1 - std::cos(t)) / (t * t) * W + (t - std::sin(t)) / (t * t * t) * W * W;
}

double RotationDeg(const PoseDelta& d) { return Eigen::Vector3d(d[0], d[1], d[2]).norm() * 180.0 / M_PI; }
double TranslationM(const PoseDelta& d) { return Eigen::Vector3d(d[3], d[4], d[5]).norm(); }

// Per-chunk partial sums in chunk order: the same bits for any thread count.
constexpr int64_t kChunk = 1 << 15;

}  // namespace

PinholeCamera CorrectedCamera(const PinholeCamera& camera, const PoseDelta& delta) {
  Eigen::Isometry3d E = Eigen::Isometry3d::Identity();
  E.linear() = RotationOf(delta);
  E.translation() = Eigen::Vector3d(delta[3], delta[4], delta[5]);
  PinholeCamera out = camera;
  out.T_world_from_cam = camera.T_world_from_cam * E;
  return out;
}

PoseDelta PoseGradient(const GaussianParamsView& rendered, const GaussianGrads& grads,
                       const PinholeCamera& corrected_camera, const PoseDelta& delta, ThreadPool& pool) {
  // Moving the camera by a small motion (w, v) in its frame renders what the fixed camera sees of
  // the Gaussians moved by the inverse motion: mean m -> m - w_w x (m - c) - v_w, rotation q -> (1,
  // -w_w / 2) * q, with c the camera centre and w_w, v_w the motion in world axes. So
  //   dL/dv_w = -sum g_m,
  //   dL/dw_w = -sum [ (m - c) x g_m + 1/2 (q_w g_qv - g_qw q_v + q_v x g_qv) ].
  const size_t n = rendered.n;
  const Eigen::Vector3d c = corrected_camera.T_world_from_cam.translation();
  const int64_t chunks = (static_cast<int64_t>(n) + kChunk - 1) / kChunk;
  std::vector<std::array<double, 6>> partial(static_cast<size_t>(chunks));
  const bool have_rotations = grads.rotations.size() >= n * 4 && rendered.rotations != nullptr;
  if (grads.means.size() >= n * 3 && rendered.means != nullptr) {
    pool.ParallelFor(chunks, 1, [&](int64_t b, int64_t e, int) {
      for (int64_t k = b; k < e; ++k) {
        double s[6] = {0, 0, 0, 0, 0, 0};  // sum of the bracket above, then sum g_m
        const size_t i0 = static_cast<size_t>(k * kChunk);
        const size_t i1 = std::min(n, i0 + static_cast<size_t>(kChunk));
        for (size_t i = i0; i < i1; ++i) {
          const double gx = grads.means[i * 3], gy = grads.means[i * 3 + 1], gz = grads.means[i * 3 + 2];
          if (gx == 0 && gy == 0 && gz == 0) continue;  // not rendered in this view
          const double rx = rendered.means[i * 3] - c.x(), ry = rendered.means[i * 3 + 1] - c.y(),
                       rz = rendered.means[i * 3 + 2] - c.z();
          s[0] += ry * gz - rz * gy;
          s[1] += rz * gx - rx * gz;
          s[2] += rx * gy - ry * gx;
          s[3] += gx;
          s[4] += gy;
          s[5] += gz;
          if (!have_rotations) continue;
          const float* q = rendered.rotations + i * 4;
          const float* g = grads.rotations.data() + i * 4;
          const double qw = q[0], qx = q[1], qy = q[2], qz = q[3];
          const double gw = g[0], gqx = g[1], gqy = g[2], gqz = g[3];
          s[0] += 0.5 * (qw * gqx - gw * qx + (qy * gqz - qz * gqy));
          s[1] += 0.5 * (qw * gqy - gw * qy + (qz * gqx - qx * gqz));
          s[2] += 0.5 * (qw * gqz - gw * qz + (qx * gqy - qy * gqx));
        }
        for (int j = 0; j < 6; ++j) partial[static_cast<size_t>(k)][j] = s[j];
      }
    });
  }
  Eigen::Vector3d dw_world = Eigen::Vector3d::Zero(), dv_world = Eigen::Vector3d::Zero();
  for (const auto& p : partial) {
    dw_world -= Eigen::Vector3d(p[0], p[1], p[2]);
    dv_world -= Eigen::Vector3d(p[3], p[4], p[5]);
  }
  // Into the corrected camera's axes, then onto the correction's parameters: a step e of the
  // translation in the corrected frame is R(w) e in the uncorrected one, a step dw of the rotation
  // vector turns the corrected camera by J_r(w) dw.
  const Eigen::Matrix3d R_cam_from_world = corrected_camera.T_world_from_cam.linear().transpose();
  const Eigen::Vector3d dw = RightJacobian(delta).transpose() * (R_cam_from_world * dw_world);
  const Eigen::Vector3d dv = RotationOf(delta) * (R_cam_from_world * dv_world);
  return {static_cast<float>(dw.x()), static_cast<float>(dw.y()), static_cast<float>(dw.z()),
          static_cast<float>(dv.x()), static_cast<float>(dv.y()), static_cast<float>(dv.z())};
}

absl::Status PreparePoseCorrections(int num_views, TrainState* st) {
  const size_t want = static_cast<size_t>(num_views) * 6;
  if (st->pose_delta.empty()) {
    st->pose_delta.assign(want, 0.0f);
    st->pose_m.assign(want, 0.0f);
    st->pose_v.assign(want, 0.0f);
    st->pose_steps.assign(static_cast<size_t>(num_views), 0);
    return absl::OkStatus();
  }
  if (st->pose_delta.size() != want) {
    return absl::FailedPreconditionError(absl::StrCat("the checkpoint's pose corrections are for ",
                                                      st->pose_delta.size() / 6, " views, this run has ", num_views));
  }
  return absl::OkStatus();
}

PoseDelta ViewCorrection(const TrainState& st, int view) {
  PoseDelta d;
  std::copy_n(&st.pose_delta[static_cast<size_t>(view) * 6], 6, d.begin());
  return d;
}

void StepPoseCorrection(const GaussianParamsView& rendered, const GaussianGrads& grads,
                        const PinholeCamera& corrected_camera, int view, const Hyper& h, ThreadPool& pool,
                        TrainState* st) {
  const size_t k = static_cast<size_t>(view) * 6;
  const PoseDelta g = PoseGradient(rendered, grads, corrected_camera, ViewCorrection(*st, view), pool);
  if (!std::all_of(g.begin(), g.end(), [](float x) { return std::isfinite(x); })) return;
  const int64_t step = ++st->pose_steps[static_cast<size_t>(view)];
  float* d = &st->pose_delta[k];
  float* m = &st->pose_m[k];
  float* v = &st->pose_v[k];
  AdamStepSmall(d, g.data(), m, v, 3, h.pose_rotation_lr, step);
  AdamStepSmall(d + 3, g.data() + 3, m + 3, v + 3, 3, h.pose_translation_lr, step);
}

std::vector<PoseCorrection> TrainedCorrections(const std::vector<View>& views, const std::vector<float>& pose_delta) {
  std::vector<PoseCorrection> out;
  for (size_t i = 0; i < views.size() && (i + 1) * 6 <= pose_delta.size(); ++i) {
    PoseCorrection c;
    c.frame = views[i].frame;
    c.camera_obs = views[i].camera_obs;
    c.time_us = views[i].time_us;
    std::copy_n(&pose_delta[i * 6], 6, c.delta.begin());
    out.push_back(c);
  }
  return out;
}

std::string CorrectionsSummary(const std::vector<PoseCorrection>& corrections) {
  double rot_sum = 0, rot_max = 0, trans_sum = 0, trans_max = 0;
  for (const PoseCorrection& c : corrections) {
    const double r = RotationDeg(c.delta);
    const double t = TranslationM(c.delta) * 100.0;
    rot_sum += r;
    trans_sum += t;
    rot_max = std::max(rot_max, r);
    trans_max = std::max(trans_max, t);
  }
  const double n = std::max<size_t>(corrections.size(), 1);
  return absl::StrCat(corrections.size(), " views, rotation mean ", absl::SixDigits(rot_sum / n), " / max ",
                      absl::SixDigits(rot_max), " deg, translation mean ", absl::SixDigits(trans_sum / n), " / max ",
                      absl::SixDigits(trans_max), " cm");
}

std::vector<PoseDelta> CorrectionsForViews(const std::vector<PoseCorrection>& trained, const std::vector<View>& views) {
  // Per camera, the trained corrections by time.
  std::map<int, std::map<int64_t, const PoseCorrection*>> by_camera;
  std::map<std::pair<int, int>, const PoseCorrection*> by_view;
  for (const PoseCorrection& c : trained) {
    by_camera[c.camera_obs][c.time_us] = &c;
    by_view[{c.frame, c.camera_obs}] = &c;
  }
  std::vector<PoseDelta> out(views.size(), PoseDelta{});
  for (size_t i = 0; i < views.size(); ++i) {
    const View& v = views[i];
    if (auto it = by_view.find({v.frame, v.camera_obs}); it != by_view.end()) {
      out[i] = it->second->delta;
      continue;
    }
    auto cam = by_camera.find(v.camera_obs);
    if (cam == by_camera.end()) continue;
    const auto& track = cam->second;
    auto after = track.lower_bound(v.time_us);
    if (after == track.begin()) {
      out[i] = after->second->delta;
      continue;
    }
    auto before = std::prev(after);
    if (after == track.end()) {
      out[i] = before->second->delta;
      continue;
    }
    const double span = static_cast<double>(after->first - before->first);
    const double a = span > 0 ? static_cast<double>(v.time_us - before->first) / span : 0.0;
    // Linear in the rotation vector: exact enough for corrections of a fraction of a degree.
    for (int j = 0; j < 6; ++j) {
      out[i][j] = static_cast<float>((1 - a) * before->second->delta[j] + a * after->second->delta[j]);
    }
  }
  return out;
}

void ApplyPoseCorrections(const std::vector<PoseCorrection>& trained, std::vector<View>* views) {
  const std::vector<PoseDelta> d = CorrectionsForViews(trained, *views);
  for (size_t i = 0; i < views->size(); ++i) (*views)[i].camera = CorrectedCamera((*views)[i].camera, d[i]);
}

absl::Status WritePoseCorrections(const std::string& dir, const std::vector<PoseCorrection>& corrections) {
  nlohmann::json list = nlohmann::json::array();
  double max_rot_deg = 0, max_trans_m = 0;
  for (const PoseCorrection& c : corrections) {
    nlohmann::json e;
    e["frame"] = c.frame;
    e["camera_obs"] = c.camera_obs;
    e["time_us"] = c.time_us;
    e["rotation_rad"] = {c.delta[0], c.delta[1], c.delta[2]};
    e["translation_m"] = {c.delta[3], c.delta[4], c.delta[5]};
    list.push_back(e);
    max_rot_deg = std::max(max_rot_deg, RotationDeg(c.delta));
    max_trans_m = std::max(max_trans_m, TranslationM(c.delta));
  }
  nlohmann::json j;
  j["corrections"] = list;
  j["max_rotation_deg"] = max_rot_deg;
  j["max_translation_m"] = max_trans_m;
  return checked_file::WriteAtomically((std::filesystem::path(dir) / kPoseCorrectionsFileName).string(),
                                       j.dump(2) + "\n");
}

absl::StatusOr<std::vector<PoseCorrection>> ReadPoseCorrections(const std::string& dir) {
  const std::string path = (std::filesystem::path(dir) / kPoseCorrectionsFileName).string();
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) return absl::NotFoundError(absl::StrCat(path, ": no such file"));
  std::ifstream in(path);
  const nlohmann::json j = nlohmann::json::parse(in, nullptr, /*allow_exceptions=*/false);
  auto bad = [&](const std::string& why) { return absl::DataLossError(absl::StrCat(path, ": ", why)); };
  if (j.is_discarded() || !j.is_object() || !j.contains("corrections") || !j["corrections"].is_array()) {
    return bad("not a pose corrections file");
  }
  auto triple = [](const nlohmann::json& e, const char* key, float* out) {
    if (!e.contains(key) || !e[key].is_array() || e[key].size() != 3) return false;
    for (int k = 0; k < 3; ++k) {
      if (!e[key][k].is_number()) return false;
      out[k] = e[key][k].get<float>();
      if (!std::isfinite(out[k])) return false;
    }
    return true;
  };
  std::vector<PoseCorrection> out;
  for (const nlohmann::json& e : j["corrections"]) {
    PoseCorrection c;
    if (!e.is_object() || !e.contains("frame") || !e["frame"].is_number_integer() || !e.contains("camera_obs") ||
        !e["camera_obs"].is_number_integer() || !e.contains("time_us") || !e["time_us"].is_number_integer() ||
        !triple(e, "rotation_rad", c.delta.data()) || !triple(e, "translation_m", c.delta.data() + 3)) {
      return bad(absl::StrCat("correction ", out.size(), " is malformed or not finite"));
    }
    c.frame = e["frame"].get<int>();
    c.camera_obs = e["camera_obs"].get<int>();
    c.time_us = e["time_us"].get<int64_t>();
    if (RotationDeg(c.delta) > 180.0 / M_PI || TranslationM(c.delta) > 100.0) {
      return bad(absl::StrCat("correction ", out.size(), " is beyond a refinement (over 1 rad or 100 m)"));
    }
    out.push_back(c);
  }
  return out;
}

}  // namespace streetsim::train
