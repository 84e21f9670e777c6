#include "scene/train/train_state.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <sstream>

#include "absl/strings/str_cat.h"
#include "scene/common/checked_file.h"
#include "scene/optim/adam_kernel.h"

namespace streetsim::train {

namespace {
constexpr int kK = 16;  // SH coefficients per channel at degree 3

inline float Sigmoid(float x) { return 1.0f / (1.0f + std::exp(-x)); }
inline float Logit(float p) { return std::log(p / (1.0f - p)); }

void ZeroLike(const GaussianStore& src, GaussianStore* dst) {
  dst->sh_degree = src.sh_degree;
  dst->means.assign(src.means.size(), 0.0f);
  dst->log_scales.assign(src.log_scales.size(), 0.0f);
  dst->rotations.assign(src.rotations.size(), 0.0f);
  dst->opacity_logits.assign(src.opacity_logits.size(), 0.0f);
  dst->sh.assign(src.sh.size(), 0.0f);
  dst->normals.clear();
}

// Calls fn(array, floats per Gaussian) for every per-Gaussian array of the state that holds n
// rows: parameters and Adam moments always, the densification statistics and the LiDAR
// reflectance (with its moments) when present. The one list that row operations follow.
template <typename Fn>
void ForEachGaussianArray(TrainState* s, size_t n, const Fn& fn) {
  for (GaussianStore* g : {&s->params, &s->adam_m, &s->adam_v}) {
    fn(g->means, 3);
    fn(g->log_scales, 3);
    fn(g->rotations, 4);
    fn(g->opacity_logits, 1);
    fn(g->sh, kK * 3);
  }
  for (std::vector<float>* v : {&s->grad_accum, &s->denom, &s->max_radii}) {
    if (v->size() == n) fn(*v, 1);
  }
  if (s->reflectance_logit.size() == n) {
    for (std::vector<float>* v : {&s->reflectance_logit, &s->reflectance_m, &s->reflectance_v}) fn(*v, 1);
  }
}

// Keeps Gaussians where keep[i] (in order), for every per-Gaussian array of the state.
void Compact(TrainState* s, const std::vector<uint8_t>& keep) {
  ForEachGaussianArray(s, keep.size(), [&](std::vector<float>& v, size_t stride) {
    size_t o = 0;
    for (size_t i = 0; i < keep.size(); ++i) {
      if (!keep[i]) continue;
      if (o != i) std::memmove(&v[o * stride], &v[i * stride], stride * sizeof(float));
      ++o;
    }
    v.resize(o * stride);
  });
}

// Row r of every per-Gaussian array becomes old row order[r].
void Permute(TrainState* s, const std::vector<uint32_t>& order) {
  std::vector<float> tmp;
  ForEachGaussianArray(s, order.size(), [&](std::vector<float>& v, size_t stride) {
    tmp.resize(order.size() * stride);
    for (size_t r = 0; r < order.size(); ++r) {
      std::memcpy(&tmp[r * stride], &v[static_cast<size_t>(order[r]) * stride], stride * sizeof(float));
    }
    v.swap(tmp);
  });
}

// Appends Gaussian i of params (with the given mean and log-scale) and zero moments.
void AppendCopy(TrainState* s, size_t i, const float* mean, const float* log_scale) {
  GaussianStore& p = s->params;
  for (int k = 0; k < 3; ++k) p.means.push_back(mean[k]);
  for (int k = 0; k < 3; ++k) p.log_scales.push_back(log_scale[k]);
  for (int k = 0; k < 4; ++k) p.rotations.push_back(p.rotations[i * 4 + k]);
  p.opacity_logits.push_back(p.opacity_logits[i]);
  for (int k = 0; k < kK * 3; ++k) p.sh.push_back(p.sh[i * kK * 3 + k]);
  if (!s->reflectance_logit.empty()) {
    s->reflectance_logit.push_back(s->reflectance_logit[i]);
    s->reflectance_m.push_back(0.0f);
    s->reflectance_v.push_back(0.0f);
  }
  for (GaussianStore* g : {&s->adam_m, &s->adam_v}) {
    g->means.insert(g->means.end(), 3, 0.0f);
    g->log_scales.insert(g->log_scales.end(), 3, 0.0f);
    g->rotations.insert(g->rotations.end(), 4, 0.0f);
    g->opacity_logits.push_back(0.0f);
    g->sh.insert(g->sh.end(), kK * 3, 0.0f);
  }
}

}  // namespace

TrainState TrainState::Init(const GaussianStore& init, double extent, int num_views, uint64_t seed) {
  TrainState s;
  s.extent = extent;
  const size_t n = init.size();
  GaussianStore& p = s.params;
  p.sh_degree = 3;
  p.means = init.means;
  p.log_scales = init.log_scales;
  p.rotations = init.rotations;
  p.opacity_logits = init.opacity_logits;
  p.sh.assign(n * kK * 3, 0.0f);
  const int K0 = init.sh_coeffs();
  for (size_t i = 0; i < n; ++i)
    for (int k = 0; k < std::min(K0, kK) * 3; ++k) p.sh[i * kK * 3 + k] = init.sh[i * K0 * 3 + k];
  ZeroLike(p, &s.adam_m);
  ZeroLike(p, &s.adam_v);
  s.grad_accum.assign(n, 0.0f);
  s.denom.assign(n, 0.0f);
  s.max_radii.assign(n, 0.0f);
  s.exposure.assign(static_cast<size_t>(num_views) * 12, 0.0f);
  for (int v = 0; v < num_views; ++v)
    for (int c = 0; c < 3; ++c) s.exposure[v * 12 + c * 4] = 1.0f;  // identity (indices 0, 4, 8)
  s.exposure_m.assign(s.exposure.size(), 0.0f);
  s.exposure_v.assign(s.exposure.size(), 0.0f);
  s.rng.seed(seed);
  return s;
}

void RenderStore(const TrainState& s, int active_degree, GaussianStore* out) {
  const size_t n = s.size();
  const int K = ShCoeffsForDegree(active_degree);
  out->sh_degree = active_degree;
  out->means = s.params.means;
  out->log_scales = s.params.log_scales;
  out->rotations = s.params.rotations;
  out->opacity_logits = s.params.opacity_logits;
  out->normals.clear();
  out->sh.resize(n * K * 3);
  for (size_t i = 0; i < n; ++i) std::memcpy(&out->sh[i * K * 3], &s.params.sh[i * kK * 3], K * 3 * sizeof(float));
}

GaussianParamsView ParamsView(const TrainState& s, int active_degree) {
  GaussianParamsView v;
  v.n = s.size();
  v.sh_degree = active_degree;
  v.sh_stride = kK;
  v.means = s.params.means.data();
  v.log_scales = s.params.log_scales.data();
  v.rotations = s.params.rotations.data();
  v.opacity_logits = s.params.opacity_logits.data();
  v.sh = s.params.sh.data();
  return v;
}

double ExpLr(double init, double final_lr, int64_t step, int max_steps) {
  const double t = std::min(std::max(static_cast<double>(step) / max_steps, 0.0), 1.0);
  return std::exp((1 - t) * std::log(init) + t * std::log(final_lr));
}

using optim::AdamRange;
constexpr float kBeta1 = optim::kAdamBeta1, kBeta2 = optim::kAdamBeta2, kEps = optim::kAdamEps;

void AdamStepSmall(float* p, const float* g, float* m, float* v, size_t n, double lr, int64_t step) {
  const double bc1 = 1 - std::pow(double(kBeta1), double(step)), bc2 = 1 - std::pow(double(kBeta2), double(step));
  AdamRange(p, g, m, v, n, static_cast<float>(lr / bc1), static_cast<float>(1 / std::sqrt(bc2)));
}

void AdamStepGaussians(TrainState* s, const GaussianGrads& grads, int active_degree, int64_t iteration,
                       const Hyper& h, ThreadPool& pool) {
  s->adam_step += 1;
  const double bc1 = 1 - std::pow(double(kBeta1), double(s->adam_step));
  const double bc2 = 1 - std::pow(double(kBeta2), double(s->adam_step));
  const float isb2 = static_cast<float>(1 / std::sqrt(bc2));
  auto step = [&](double lr) { return static_cast<float>(lr / bc1); };
  const float xyz_lr = step(ExpLr(h.xyz_lr_init * s->extent, h.xyz_lr_final * s->extent, iteration, h.lr_decay_steps));
  const size_t n = s->size();
  const int Ka = ShCoeffsForDegree(active_degree);
  GaussianStore& p = s->params;
  GaussianStore& m = s->adam_m;
  GaussianStore& v = s->adam_v;
  pool.ParallelFor(static_cast<int64_t>(n), 8192, [&](int64_t b, int64_t e, int) {
    const size_t len = e - b;
    AdamRange(&p.means[b * 3], &grads.means[b * 3], &m.means[b * 3], &v.means[b * 3], len * 3, xyz_lr, isb2);
    AdamRange(&p.log_scales[b * 3], &grads.log_scales[b * 3], &m.log_scales[b * 3], &v.log_scales[b * 3], len * 3,
              step(h.scaling_lr), isb2);
    AdamRange(&p.rotations[b * 4], &grads.rotations[b * 4], &m.rotations[b * 4], &v.rotations[b * 4], len * 4,
              step(h.rotation_lr), isb2);
    AdamRange(&p.opacity_logits[b], &grads.opacity_logits[b], &m.opacity_logits[b], &v.opacity_logits[b], len,
              step(h.opacity_lr), isb2);
    // SH: one pass over the chunk's [len * 48] coefficients; per-coefficient step size (f_dc for
    // the 3 DC terms, f_rest for the others) and zero gradient beyond the active degree.
    alignas(64) float lr_tab[kK * 3];
    for (int k = 0; k < kK * 3; ++k) lr_tab[k] = k < 3 ? step(h.f_dc_lr) : step(h.f_rest_lr);
    const int ka3 = Ka * 3;
    for (int64_t i = b; i < e; ++i) {
      float* __restrict pp = &p.sh[i * kK * 3];
      float* __restrict mm = &m.sh[i * kK * 3];
      float* __restrict vv = &v.sh[i * kK * 3];
      const float* __restrict gg = &grads.sh[i * ka3];
      for (int k = 0; k < ka3; ++k) {
        const float gi = gg[k];
        const float mi = kBeta1 * mm[k] + (1 - kBeta1) * gi;
        const float vi = kBeta2 * vv[k] + (1 - kBeta2) * gi * gi;
        mm[k] = mi;
        vv[k] = vi;
        pp[k] -= lr_tab[k] * mi / (std::sqrt(vi) * isb2 + kEps);
      }
      for (int k = ka3; k < kK * 3; ++k) {
        const float mi = kBeta1 * mm[k];
        const float vi = kBeta2 * vv[k];
        mm[k] = mi;
        vv[k] = vi;
        pp[k] -= lr_tab[k] * mi / (std::sqrt(vi) * isb2 + kEps);
      }
    }
  });
}

void AccumulateStats(TrainState* s, const GaussianGrads& grads, int width, int height) {
  const size_t n = s->size();
  const float hw = 0.5f * width, hh = 0.5f * height;  // pixel -> NDC gradients, as 3DGS
  for (size_t i = 0; i < n; ++i) {
    if (!(grads.radii[i] > 0)) continue;
    s->max_radii[i] = std::max(s->max_radii[i], grads.radii[i]);
    const float gx = grads.means2d[i * 2] * hw, gy = grads.means2d[i * 2 + 1] * hh;
    s->grad_accum[i] += std::sqrt(gx * gx + gy * gy);
    s->denom[i] += 1;
  }
}

void DensifyAndPrune(TrainState* s, const Hyper& h, int64_t iteration, size_t* added, size_t* removed) {
  const size_t n0 = s->size();
  *added = *removed = 0;
  const float tau = static_cast<float>(h.densify_grad_threshold);
  const float dense = static_cast<float>(h.percent_dense * s->extent);
  std::vector<uint8_t> split_parent(n0, 0);
  if (n0 < h.max_gaussians) {
    std::vector<float> g(n0);
    for (size_t i = 0; i < n0; ++i) g[i] = s->denom[i] > 0 ? s->grad_accum[i] / s->denom[i] : 0.0f;
    auto max_scale = [&](size_t i) {
      const float* l = &s->params.log_scales[i * 3];
      return std::exp(std::max(l[0], std::max(l[1], l[2])));
    };
    // Clone: small Gaussians with a large view-space gradient, duplicated unchanged.
    for (size_t i = 0; i < n0; ++i) {
      if (g[i] >= tau && max_scale(i) <= dense) {
        const float mean[3] = {s->params.means[i * 3], s->params.means[i * 3 + 1], s->params.means[i * 3 + 2]};
        const float ls[3] = {s->params.log_scales[i * 3], s->params.log_scales[i * 3 + 1], s->params.log_scales[i * 3 + 2]};
        AppendCopy(s, i, mean, ls);
        ++*added;
      }
    }
    // Split: large ones become 2 children sampled from the Gaussian, scale / 1.6 (3DGS's order:
    // all first children, then all second children), parents removed below.
    std::vector<size_t> parents;
    for (size_t i = 0; i < n0; ++i)
      if (g[i] >= tau && max_scale(i) > dense) parents.push_back(i);
    std::normal_distribution<float> normal(0.0f, 1.0f);
    for (int copy = 0; copy < 2; ++copy) {
      for (size_t i : parents) {
        const float* q = &s->params.rotations[i * 4];
        const float qn = 1.0f / std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
        const float w = q[0] * qn, x = q[1] * qn, y = q[2] * qn, z = q[3] * qn;
        const float R[9] = {1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)};
        float e[3], mean[3], ls[3];
        for (int k = 0; k < 3; ++k) e[k] = normal(s->rng) * std::exp(s->params.log_scales[i * 3 + k]);
        for (int r = 0; r < 3; ++r)
          mean[r] = s->params.means[i * 3 + r] + R[r * 3] * e[0] + R[r * 3 + 1] * e[1] + R[r * 3 + 2] * e[2];
        for (int k = 0; k < 3; ++k) ls[k] = s->params.log_scales[i * 3 + k] - std::log(1.6f);
        AppendCopy(s, i, mean, ls);
        ++*added;
      }
    }
    for (size_t i : parents) split_parent[i] = 1;
    // Statistics restart after any densification.
    const size_t n1 = s->size();
    s->grad_accum.assign(n1, 0.0f);
    s->denom.assign(n1, 0.0f);
    s->max_radii.assign(n1, 0.0f);
  }
  // Prune: split parents, near-transparent Gaussians, and (after the first opacity reset) ones
  // wider than a tenth of the scene. Not 3DGS's screen-size rule (max_radii2D > 20 px): its
  // reference zeroes max_radii2D when it densifies, before it prunes, so the rule never fires
  // there, nor did it here, except when the Gaussian cap skipped densification: then it pruned 783k
  // of 2.0M Gaussians at once (the odometry excerpt at full resolution, iteration 9700), and the
  // divergence guard stopped the run.
  const size_t n1 = s->size();
  std::vector<uint8_t> keep(n1, 1);
  const bool big = iteration > h.opacity_reset_interval;
  for (size_t i = 0; i < n1; ++i) {
    if (i < n0 && split_parent[i]) keep[i] = 0;
    if (Sigmoid(s->params.opacity_logits[i]) < h.min_opacity) keep[i] = 0;
    if (big) {
      const float* l = &s->params.log_scales[i * 3];
      if (std::exp(std::max(l[0], std::max(l[1], l[2]))) > 0.1 * s->extent) keep[i] = 0;
    }
  }
  for (uint8_t k : keep) *removed += !k;
  if (*removed) Compact(s, keep);
}

absl::Status PermuteRows(TrainState* s, const std::vector<uint32_t>& order) {
  const size_t n = s->size();
  if (order.size() != n) {
    return absl::InvalidArgumentError(absl::StrCat("PermuteRows: ", order.size(), " rows for ", n, " Gaussians"));
  }
  std::vector<uint8_t> seen(n, 0);
  for (uint32_t i : order) {
    if (i >= n || seen[i]) return absl::InvalidArgumentError("PermuteRows: not a permutation");
    seen[i] = 1;
  }
  Permute(s, order);
  return absl::OkStatus();
}

void ResetOpacity(TrainState* s) {
  const float cap = Logit(0.01f);
  for (float& o : s->params.opacity_logits) o = std::min(o, cap);
  std::fill(s->adam_m.opacity_logits.begin(), s->adam_m.opacity_logits.end(), 0.0f);
  std::fill(s->adam_v.opacity_logits.begin(), s->adam_v.opacity_logits.end(), 0.0f);
}

// ---- checkpoints ----
namespace {
constexpr char kMagic[8] = {'S', 'S', 'T', 'R', 'N', '0', '0', '1'};
// Optional trailing sections (older checkpoints end before them): the LiDAR reflectance logits,
// then the camera pose corrections.
constexpr char kReflectanceTag[8] = {'R', 'E', 'F', 'L', 'O', 'G', '0', '1'};
constexpr char kPoseTag[8] = {'P', 'O', 'S', 'E', 'R', 'F', '0', '1'};

bool AllFinite(const std::vector<float>& v) {
  return std::all_of(v.begin(), v.end(), [](float x) { return std::isfinite(x); });
}

class Writer {
 public:
  void Raw(const void* p, size_t n) { buf_.append(static_cast<const char*>(p), n); }
  template <typename T>
  void Pod(const T& v) { Raw(&v, sizeof(T)); }
  template <typename T>
  void Vec(const std::vector<T>& v) {
    Pod<uint64_t>(v.size());
    Raw(v.data(), v.size() * sizeof(T));
  }
  void Str(const std::string& s) {
    Pod<uint64_t>(s.size());
    Raw(s.data(), s.size());
  }
  std::string buf_;
};

class Reader {
 public:
  explicit Reader(std::string b) : buf_(std::move(b)) {}
  bool Raw(void* p, size_t n) {
    if (pos_ + n > buf_.size()) return ok_ = false;
    std::memcpy(p, buf_.data() + pos_, n);
    pos_ += n;
    return true;
  }
  template <typename T>
  bool Pod(T* v) { return Raw(v, sizeof(T)); }
  template <typename T>
  bool Vec(std::vector<T>* v) {
    uint64_t n = 0;
    if (!Pod(&n) || n > (buf_.size() - pos_) / sizeof(T)) return ok_ = false;
    v->resize(n);
    return Raw(v->data(), n * sizeof(T));
  }
  bool Str(std::string* s) {
    uint64_t n = 0;
    if (!Pod(&n) || n > buf_.size() - pos_) return ok_ = false;
    s->assign(buf_.data() + pos_, n);
    pos_ += n;
    return true;
  }
  bool ok() const { return ok_; }
  bool at_end() const { return pos_ == buf_.size(); }

 private:
  std::string buf_;
  size_t pos_ = 0;
  bool ok_ = true;
};

void PutStore(Writer& w, const GaussianStore& g) {
  w.Pod<int32_t>(g.sh_degree);
  w.Vec(g.means);
  w.Vec(g.log_scales);
  w.Vec(g.rotations);
  w.Vec(g.opacity_logits);
  w.Vec(g.sh);
}
bool GetStore(Reader& r, GaussianStore* g) {
  int32_t d = 0;
  return r.Pod(&d) && (g->sh_degree = d, true) && r.Vec(&g->means) && r.Vec(&g->log_scales) &&
         r.Vec(&g->rotations) && r.Vec(&g->opacity_logits) && r.Vec(&g->sh);
}
}  // namespace

absl::Status SaveCheckpoint(const TrainState& s, const std::string& path) {
  Writer w;
  w.Raw(kMagic, 8);
  w.Pod<int64_t>(s.iteration);
  w.Pod<double>(s.extent);
  PutStore(w, s.params);
  PutStore(w, s.adam_m);
  PutStore(w, s.adam_v);
  w.Pod<int64_t>(s.adam_step);
  w.Vec(s.grad_accum);
  w.Vec(s.denom);
  w.Vec(s.max_radii);
  w.Raw(s.sky, sizeof(s.sky));
  w.Raw(s.sky_m, sizeof(s.sky_m));
  w.Raw(s.sky_v, sizeof(s.sky_v));
  w.Pod<int64_t>(s.aux_step);
  w.Vec(s.exposure);
  w.Vec(s.exposure_m);
  w.Vec(s.exposure_v);
  w.Vec(s.view_queue);
  std::ostringstream rng;
  rng << s.rng;
  w.Str(rng.str());
  w.Vec(s.curve);
  if (!s.reflectance_logit.empty()) {
    w.Raw(kReflectanceTag, 8);
    w.Vec(s.reflectance_logit);
    w.Vec(s.reflectance_m);
    w.Vec(s.reflectance_v);
    w.Pod<int64_t>(s.reflectance_step);
  }
  if (!s.pose_delta.empty()) {
    w.Raw(kPoseTag, 8);
    w.Vec(s.pose_delta);
    w.Vec(s.pose_m);
    w.Vec(s.pose_v);
    w.Vec(s.pose_steps);
  }
  return checked_file::WriteAtomically(path, w.buf_);
}

absl::StatusOr<int64_t> PeekCheckpointIteration(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  if (!f) return absl::NotFoundError(absl::StrCat("cannot open checkpoint ", path));
  char head[8 + sizeof(int64_t)];
  if (!f.read(head, sizeof(head)) || std::memcmp(head, kMagic, 8) != 0) {
    return absl::DataLossError(absl::StrCat(path, ": not a streetsim training checkpoint"));
  }
  int64_t iteration = 0;
  std::memcpy(&iteration, head + 8, sizeof(iteration));
  if (iteration < 0) return absl::DataLossError(absl::StrCat(path, ": corrupt iteration ", iteration));
  return iteration;
}

absl::StatusOr<TrainState> LoadCheckpoint(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  if (!f) return absl::NotFoundError(absl::StrCat("cannot open checkpoint ", path));
  std::string bytes((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  Reader r(std::move(bytes));
  char magic[8];
  if (!r.Raw(magic, 8) || std::memcmp(magic, kMagic, 8) != 0) {
    return absl::DataLossError(absl::StrCat(path, ": not a streetsim training checkpoint"));
  }
  TrainState s;
  std::string rng;
  const bool ok = r.Pod(&s.iteration) && r.Pod(&s.extent) && GetStore(r, &s.params) && GetStore(r, &s.adam_m) &&
                  GetStore(r, &s.adam_v) && r.Pod(&s.adam_step) && r.Vec(&s.grad_accum) && r.Vec(&s.denom) &&
                  r.Vec(&s.max_radii) && r.Raw(s.sky, sizeof(s.sky)) && r.Raw(s.sky_m, sizeof(s.sky_m)) &&
                  r.Raw(s.sky_v, sizeof(s.sky_v)) && r.Pod(&s.aux_step) && r.Vec(&s.exposure) &&
                  r.Vec(&s.exposure_m) && r.Vec(&s.exposure_v) && r.Vec(&s.view_queue) && r.Str(&rng) &&
                  r.Vec(&s.curve);
  // Optional trailing sections, each at most once, in the order written.
  bool sections_ok = true;
  int last_section = -1;
  while (ok && sections_ok && !r.at_end()) {
    char tag[8];
    if (!r.Raw(tag, 8)) {
      sections_ok = false;
    } else if (std::memcmp(tag, kReflectanceTag, 8) == 0 && last_section < 0) {
      last_section = 0;
      sections_ok = r.Vec(&s.reflectance_logit) && r.Vec(&s.reflectance_m) && r.Vec(&s.reflectance_v) &&
                    r.Pod(&s.reflectance_step);
    } else if (std::memcmp(tag, kPoseTag, 8) == 0 && last_section < 1) {
      last_section = 1;
      sections_ok = r.Vec(&s.pose_delta) && r.Vec(&s.pose_m) && r.Vec(&s.pose_v) && r.Vec(&s.pose_steps);
    } else {
      sections_ok = false;
    }
  }
  if (!ok || !sections_ok) return absl::DataLossError(absl::StrCat(path, ": truncated or corrupt checkpoint"));
  std::istringstream in(rng);
  in >> s.rng;
  if (!in) return absl::DataLossError(absl::StrCat(path, ": corrupt RNG state"));
  const size_t n = s.params.size();
  if (s.params.Validate().ok() == false || s.params.sh_degree != 3 || s.adam_m.sh.size() != s.params.sh.size() ||
      s.adam_v.sh.size() != s.params.sh.size() || s.grad_accum.size() != n || s.denom.size() != n ||
      s.max_radii.size() != n || s.exposure.size() != s.exposure_m.size() ||
      !(s.reflectance_logit.empty() || s.reflectance_logit.size() == n) ||
      s.reflectance_m.size() != s.reflectance_logit.size() || s.reflectance_v.size() != s.reflectance_logit.size() ||
      s.pose_delta.size() % 6 != 0 || s.pose_m.size() != s.pose_delta.size() ||
      s.pose_v.size() != s.pose_delta.size() || s.pose_steps.size() * 6 != s.pose_delta.size() ||
      !AllFinite(s.pose_delta)) {
    return absl::DataLossError(absl::StrCat(path, ": inconsistent checkpoint"));
  }
  return s;
}

}  // namespace streetsim::train
