#include "scene/actors/actor_edits.h"

#include <cmath>

#include "absl/strings/str_cat.h"
#include "scene/actors/rigid_gaussians.h"

namespace streetsim::actors {
namespace {

const char* KindName(ActorEdit::Kind k) {
  switch (k) {
    case ActorEdit::Kind::kRemove: return "remove";
    case ActorEdit::Kind::kMove: return "move";
    case ActorEdit::Kind::kInsert: return "insert";
  }
  return "?";
}

bool IsRigid(const Eigen::Isometry3d& T) {
  const Eigen::Matrix3d R = T.linear();
  if (!R.allFinite() || !T.translation().allFinite()) return false;
  return (R.transpose() * R - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff() < 1e-5 &&
         std::abs(R.determinant() - 1) < 1e-5;
}

}  // namespace

absl::Status ValidateActorEdits(const ActorSet& set, const std::vector<ActorEdit>& edits) {
  if (edits.size() > kMaxActorEdits) {
    return absl::InvalidArgumentError(
        absl::StrCat(edits.size(), " actor edits; at most ", kMaxActorEdits, " per request"));
  }
  std::vector<int> edited;
  for (size_t e = 0; e < edits.size(); ++e) {
    const ActorEdit& edit = edits[e];
    const std::string what = absl::StrCat("actor_edits[", e, "] (", KindName(edit.kind), " actor ", edit.actor_id, ")");
    if (set.Find(edit.actor_id) == nullptr) {
      return absl::InvalidArgumentError(absl::StrCat(what, ": the scene has no such actor (GetScene lists ",
                                                     set.actors.size(), ")"));
    }
    if (edit.kind != ActorEdit::Kind::kInsert) {
      if (std::find(edited.begin(), edited.end(), edit.actor_id) != edited.end()) {
        return absl::InvalidArgumentError(absl::StrCat(what, ": the actor is removed or moved twice"));
      }
      edited.push_back(edit.actor_id);
    }
    if (edit.kind == ActorEdit::Kind::kRemove) {
      if (!edit.trajectory.empty()) return absl::InvalidArgumentError(absl::StrCat(what, ": a removal takes no trajectory"));
      continue;
    }
    if (edit.trajectory.empty() || edit.trajectory.size() > kMaxEditPoses) {
      return absl::InvalidArgumentError(
          absl::StrCat(what, ": needs 1 to ", kMaxEditPoses, " trajectory poses, not ", edit.trajectory.size()));
    }
    for (size_t k = 0; k < edit.trajectory.size(); ++k) {
      if (!IsRigid(edit.trajectory[k].T_world_from_actor)) {
        return absl::InvalidArgumentError(
            absl::StrCat(what, ": pose ", k, " is not finite or its rotation is not a unit quaternion"));
      }
      if (k > 0 && edit.trajectory[k].time_us <= edit.trajectory[k - 1].time_us) {
        return absl::InvalidArgumentError(absl::StrCat(what, ": pose ", k, "'s time does not increase"));
      }
    }
  }
  return absl::OkStatus();
}

EditedScene ApplyActorEdits(const GaussianStore& at_time, const std::vector<float>* reflectance,
                            const ActorSet& set, const std::vector<ActorEdit>& edits, int64_t time_us) {
  const size_t n = at_time.size();
  std::vector<uint8_t> drop(n, 0);
  for (const ActorEdit& e : edits) {
    if (e.kind == ActorEdit::Kind::kInsert) continue;
    const Actor* a = set.Find(e.actor_id);
    for (uint32_t r : a->body_rows) drop[r] = 1;
    for (uint32_t r : a->ghost_rows) drop[r] = 1;
  }
  std::vector<uint32_t> kept;
  kept.reserve(n);
  for (size_t i = 0; i < n; ++i) {
    if (!drop[i]) kept.push_back(static_cast<uint32_t>(i));
  }
  EditedScene out;
  out.gaussians.sh_degree = at_time.sh_degree;
  AppendRows(at_time, kept.data(), kept.size(), &out.gaussians);
  if (reflectance != nullptr) {
    out.reflectance.emplace();
    out.reflectance->reserve(kept.size());
    for (uint32_t r : kept) out.reflectance->push_back((*reflectance)[r]);
  }
  for (const ActorEdit& e : edits) {
    if (e.kind == ActorEdit::Kind::kRemove) continue;
    const Actor* a = set.Find(e.actor_id);
    const size_t first = out.gaussians.size();
    std::vector<uint32_t> rows(a->gaussians.size());
    for (size_t i = 0; i < rows.size(); ++i) rows[i] = static_cast<uint32_t>(i);
    AppendRows(a->gaussians, rows.data(), rows.size(), &out.gaussians);
    TransformGaussians(PoseAt(e.trajectory, time_us), &out.gaussians, first, out.gaussians.size());
    if (out.reflectance) {
      for (uint32_t r : a->body_rows) out.reflectance->push_back((*reflectance)[r]);
    }
  }
  return out;
}

}  // namespace streetsim::actors
