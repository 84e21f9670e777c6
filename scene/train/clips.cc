#include "scene/train/clips.h"

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"

namespace streetsim::train {
namespace {

namespace fs = std::filesystem;

constexpr int kManifestVersion = 1;
// clips.json lists a few hundred clips at most; anything far larger is not ours.
constexpr uintmax_t kMaxManifestBytes = 16u << 20;
constexpr int kMaxFrames = 100'000'000;

absl::Status Bad(const std::string& path, const std::string& why) {
  return absl::DataLossError(absl::StrCat(path, ": ", why));
}

}  // namespace

absl::StatusOr<std::vector<ClipRange>> PlanClips(int num_frames, int clip_frames) {
  if (num_frames < 1) return absl::InvalidArgumentError("the log has no frames to split into clips");
  if (clip_frames < 0 || (clip_frames > 0 && clip_frames < kMinClipFrames)) {
    return absl::InvalidArgumentError(absl::StrCat("--clip-frames must be 0 (one clip over the whole log) or >= ",
                                                   kMinClipFrames, ", not ", clip_frames));
  }
  if (clip_frames == 0 || num_frames <= clip_frames) return std::vector<ClipRange>{{0, num_frames}};
  std::vector<ClipRange> plan;
  const int full = num_frames / clip_frames, rest = num_frames % clip_frames;
  for (int k = 0; k < full; ++k) plan.push_back({k * clip_frames, (k + 1) * clip_frames});
  if (rest >= (clip_frames + 1) / 2) {
    plan.push_back({full * clip_frames, num_frames});
  } else {
    plan.back().end_frame = num_frames;  // a short tail joins the last full clip
  }
  return plan;
}

ClipRange TrainedFrames(const ClipRange& frames, int overlap_frames, int num_frames) {
  return {std::max(0, frames.first_frame - overlap_frames), std::min(num_frames, frames.end_frame + overlap_frames)};
}

absl::Status CheckClipOverlap(int clip_frames, int overlap_frames) {
  if (overlap_frames < 0 || overlap_frames > clip_frames / 2) {
    return absl::InvalidArgumentError(absl::StrCat("--clip-overlap must be in 0..", clip_frames / 2,
                                                   " (half of --clip-frames ", clip_frames, "), not ", overlap_frames));
  }
  return absl::OkStatus();
}

DriveLog ClipLog(const DriveLog& log, const ClipRange& r) {
  DriveLog sub = log;
  sub.frames.assign(log.frames.begin() + r.first_frame, log.frames.begin() + r.end_frame);
  return sub;
}

std::string ClipDirName(int index) {
  char buf[32];
  std::snprintf(buf, sizeof(buf), "clip_%03d", index);
  return buf;
}

ClipSet MakeClipSet(const DriveLog& log, int clip_frames, const std::vector<ClipRange>& plan, int overlap_frames) {
  ClipSet set;
  set.clip_frames = clip_frames;
  set.overlap_frames = overlap_frames;
  set.num_frames = static_cast<int>(log.frames.size());
  for (size_t k = 0; k < plan.size(); ++k) {
    ClipEntry e;
    e.frames = plan[k];
    e.start_us = log.frames[plan[k].first_frame].time_us;
    e.end_us = log.frames[plan[k].end_frame - 1].time_us;
    e.dir = ClipDirName(static_cast<int>(k));
    set.clips.push_back(e);
  }
  return set;
}

absl::Status WriteClipSet(const ClipSet& set, const std::string& dir) {
  nlohmann::json j;
  j["version"] = kManifestVersion;
  j["clip_frames"] = set.clip_frames;
  j["overlap_frames"] = set.overlap_frames;
  j["num_frames"] = set.num_frames;
  j["clips"] = nlohmann::json::array();
  for (size_t k = 0; k < set.clips.size(); ++k) {
    const ClipEntry& c = set.clips[k];
    j["clips"].push_back({{"index", k},
                          {"dir", c.dir},
                          {"frames", {c.frames.first_frame, c.frames.end_frame}},
                          {"trained_frames", {set.trained(k).first_frame, set.trained(k).end_frame}},
                          {"time_range_us", {c.start_us, c.end_us}},
                          {"done", c.done}});
  }
  const std::string path = (fs::path(dir) / kClipManifestName).string();
  const std::string tmp = path + ".tmp";
  {
    std::ofstream f(tmp, std::ios::trunc);
    f << j.dump(2) << "\n";
    if (!f) return absl::InternalError(absl::StrCat("cannot write ", tmp));
  }
  std::error_code ec;
  fs::rename(tmp, path, ec);
  if (ec) return absl::InternalError(absl::StrCat("cannot rename ", tmp, ": ", ec.message()));
  return absl::OkStatus();
}

absl::StatusOr<std::optional<ClipSet>> ReadClipSet(const std::string& dir) {
  const std::string path = (fs::path(dir) / kClipManifestName).string();
  std::error_code ec;
  if (!fs::exists(path, ec)) return std::optional<ClipSet>();
  const uintmax_t bytes = fs::file_size(path, ec);
  if (ec) return Bad(path, absl::StrCat("cannot read: ", ec.message()));
  if (bytes > kMaxManifestBytes) return Bad(path, absl::StrCat(bytes, " bytes, too large for a clip manifest"));
  std::ifstream f(path, std::ios::binary);
  if (!f) return Bad(path, "cannot open");
  std::stringstream text;
  text << f.rdbuf();
  ClipSet set;
  try {
    const nlohmann::json j = nlohmann::json::parse(text.str());
    if (j.at("version").get<int>() != kManifestVersion) {
      return Bad(path, absl::StrCat("unknown version ", j.at("version").dump()));
    }
    set.clip_frames = j.at("clip_frames").get<int>();
    set.num_frames = j.at("num_frames").get<int>();
    set.overlap_frames = j.value("overlap_frames", 0);
    const nlohmann::json& clips = j.at("clips");
    if (!clips.is_array() || clips.empty()) return Bad(path, "\"clips\" must be a non-empty array");
    if (set.num_frames < 1 || set.num_frames > kMaxFrames || set.clip_frames < 0 ||
        !CheckClipOverlap(set.clip_frames, set.overlap_frames).ok() ||
        clips.size() > static_cast<size_t>(set.num_frames)) {
      return Bad(path, "implausible clip_frames / num_frames / number of clips");
    }
    for (size_t k = 0; k < clips.size(); ++k) {
      const nlohmann::json& c = clips[k];
      ClipEntry e;
      e.dir = c.at("dir").get<std::string>();
      const nlohmann::json& fr = c.at("frames");
      const nlohmann::json& tr = c.at("time_range_us");
      if (fr.size() != 2 || tr.size() != 2) {
        return Bad(path, absl::StrCat("clip ", k, ": frames / time_range_us need 2 numbers"));
      }
      e.frames = {fr.at(0).get<int>(), fr.at(1).get<int>()};
      e.start_us = tr.at(0).get<int64_t>();
      e.end_us = tr.at(1).get<int64_t>();
      e.done = c.at("done").get<bool>();
      if (c.at("index").get<int64_t>() != static_cast<int64_t>(k)) {
        return Bad(path, absl::StrCat("clip ", k, ": wrong index"));
      }
      // Only the canonical name: no separators, no "..", no absolute path can get through.
      if (e.dir != ClipDirName(static_cast<int>(k))) {
        return Bad(path, absl::StrCat("clip ", k, ": directory '", e.dir.substr(0, 64), "' is not ",
                                      ClipDirName(static_cast<int>(k))));
      }
      const int expected_first = k == 0 ? 0 : set.clips.back().frames.end_frame;
      if (e.frames.first_frame != expected_first || e.frames.end_frame <= e.frames.first_frame ||
          e.frames.end_frame > set.num_frames) {
        return Bad(path, absl::StrCat("clip ", k, ": frames [", e.frames.first_frame, ", ", e.frames.end_frame,
                                      ") do not follow the previous clip inside the log's ", set.num_frames,
                                      " frames"));
      }
      if (e.end_us < e.start_us || (k > 0 && e.start_us < set.clips.back().end_us)) {
        return Bad(path, absl::StrCat("clip ", k, ": time range out of order"));
      }
      if (c.contains("trained_frames")) {
        const nlohmann::json& tf = c.at("trained_frames");
        const ClipRange trained = TrainedFrames(e.frames, set.overlap_frames, set.num_frames);
        if (tf.size() != 2 || !(ClipRange{tf.at(0).get<int>(), tf.at(1).get<int>()} == trained)) {
          return Bad(path, absl::StrCat("clip ", k, ": trained_frames are not its frames widened by overlap_frames ",
                                        set.overlap_frames));
        }
      }
      set.clips.push_back(std::move(e));
    }
    if (set.clips.back().frames.end_frame != set.num_frames) return Bad(path, "the clips do not cover the log");
  } catch (const std::exception& e) {
    return Bad(path, e.what());
  }
  return std::optional<ClipSet>(std::move(set));
}

int PickClip(const ClipSet& set, int64_t time_us) {
  int best = 0;
  uint64_t best_gap = UINT64_MAX;
  const uint64_t t = static_cast<uint64_t>(time_us);
  for (size_t k = 0; k < set.clips.size(); ++k) {
    const ClipEntry& c = set.clips[k];
    // Distance to the range (0 inside), unsigned so that no int64 time overflows; the ranges are
    // in time order, so the strict < keeps the earlier clip on a tie.
    const uint64_t gap = time_us < c.start_us   ? static_cast<uint64_t>(c.start_us) - t
                         : time_us > c.end_us ? t - static_cast<uint64_t>(c.end_us)
                                              : 0;
    if (gap < best_gap) best = static_cast<int>(k), best_gap = gap;
  }
  return best;
}

absl::StatusOr<std::string> ClipPath(const std::string& dir, const ClipEntry& clip) {
  const fs::path p = fs::path(dir) / clip.dir;
  std::error_code ec;
  const fs::path root = fs::canonical(dir, ec);
  if (ec) return absl::NotFoundError(absl::StrCat(dir, ": ", ec.message()));
  const fs::path real = fs::canonical(p, ec);
  if (ec || !fs::is_directory(real, ec)) {
    return absl::NotFoundError(
        absl::StrCat(p.string(), ": clip directory missing (listed in ", kClipManifestName, ")"));
  }
  const std::string r = root.string(), c = real.string();
  if (c.size() <= r.size() || c.compare(0, r.size(), r) != 0 || c[r.size()] != '/') {
    return absl::DataLossError(absl::StrCat(p.string(), ": resolves outside ", dir));
  }
  return p.string();
}

absl::StatusOr<std::string> SceneDirForTime(const std::string& dir, std::optional<int64_t> time_us) {
  absl::StatusOr<std::optional<ClipSet>> set = ReadClipSet(dir);
  if (!set.ok()) return set.status();
  if (!*set) return dir;
  const ClipSet& s = **set;
  return ClipPath(dir, s.clips[time_us ? PickClip(s, *time_us) : 0]);
}

std::vector<std::vector<size_t>> GroupViewsByClip(const ClipSet& set, const std::vector<View>& views) {
  std::vector<std::vector<size_t>> groups(set.clips.size());
  for (size_t i = 0; i < views.size(); ++i) groups[PickClip(set, views[i].time_us)].push_back(i);
  return groups;
}

EvalResult MergeEvalResults(const std::vector<EvalResult>& parts) {
  EvalResult r;
  for (const EvalResult& p : parts) r.frames.insert(r.frames.end(), p.frames.begin(), p.frames.end());
  auto mean_of = [&](double FrameMetrics::*m, bool all) {
    double sum = 0;
    int n = 0;
    for (const FrameMetrics& f : r.frames) {
      if (all || f.*m >= 0) sum += f.*m, ++n;
    }
    return n ? sum / n : (all ? 0.0 : -1.0);
  };
  r.mean.name = "mean";
  r.mean.psnr = mean_of(&FrameMetrics::psnr, true);
  r.mean.ssim = mean_of(&FrameMetrics::ssim, true);
  r.mean.depth_median_abs_m = mean_of(&FrameMetrics::depth_median_abs_m, false);
  r.mean.depth_within_5pct = mean_of(&FrameMetrics::depth_within_5pct, false);
  r.mean.psnr_dynamic = mean_of(&FrameMetrics::psnr_dynamic, false);
  r.mean.psnr_static = mean_of(&FrameMetrics::psnr_static, false);
  return r;
}

LidarEvalResult MergeLidarEvalResults(const std::vector<LidarEvalResult>& parts) {
  LidarEvalResult r;
  for (const LidarEvalResult& p : parts) r.frames.insert(r.frames.end(), p.frames.begin(), p.frames.end());
  auto mean_of = [&](double LidarFrameMetrics::*m) {
    double sum = 0;
    int n = 0;
    for (const LidarFrameMetrics& f : r.frames) {
      if (f.*m >= 0) sum += f.*m, ++n;
    }
    return n ? sum / n : -1.0;
  };
  r.mean.range_median_abs_m = mean_of(&LidarFrameMetrics::range_median_abs_m);
  r.mean.chamfer_m = mean_of(&LidarFrameMetrics::chamfer_m);
  r.mean.drop_accuracy = mean_of(&LidarFrameMetrics::drop_accuracy);
  r.mean.intensity_rmse = mean_of(&LidarFrameMetrics::intensity_rmse);
  for (const LidarFrameMetrics& f : r.frames) r.mean.rays += f.rays;
  return r;
}

}  // namespace streetsim::train
