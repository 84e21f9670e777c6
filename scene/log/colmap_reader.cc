#include "scene/log/colmap_reader.h"

#include <unistd.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>

#include <opencv2/imgcodecs.hpp>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "scene/log/text_util.h"

namespace streetsim {
namespace {

namespace fs = std::filesystem;

struct ModelInfo {
  int id;
  const char* name;
  int num_params;
};
// COLMAP's model ids (binary files store the id, text files the name).
constexpr ModelInfo kModels[] = {{0, "SIMPLE_PINHOLE", 3}, {1, "PINHOLE", 4}, {2, "SIMPLE_RADIAL", 4},
                                 {3, "RADIAL", 5},         {4, "OPENCV", 8}};

const ModelInfo* ModelByName(const std::string& name) {
  for (const ModelInfo& m : kModels) {
    if (name == m.name) return &m;
  }
  return nullptr;
}
const ModelInfo* ModelById(int id) {
  for (const ModelInfo& m : kModels) {
    if (id == m.id) return &m;
  }
  return nullptr;
}

std::vector<std::string> Tokens(const std::string& line) {
  std::vector<std::string> out;
  size_t i = 0;
  while (i < line.size()) {
    while (i < line.size() && (line[i] == ' ' || line[i] == '\t' || line[i] == '\r')) ++i;
    size_t j = i;
    while (j < line.size() && line[j] != ' ' && line[j] != '\t' && line[j] != '\r') ++j;
    if (j > i) out.push_back(line.substr(i, j - i));
    i = j;
  }
  return out;
}

absl::Status ValidateCamera(const ColmapCamera& cam, const std::string& where) {
  const ModelInfo* m = ModelByName(cam.model);
  if (m == nullptr) {
    return absl::InvalidArgumentError(absl::StrCat(where, ": camera model '", cam.model,
                                                   "' not supported (SIMPLE_PINHOLE, PINHOLE, "
                                                   "SIMPLE_RADIAL, RADIAL, OPENCV)"));
  }
  if (static_cast<int>(cam.params.size()) != m->num_params) {
    return absl::InvalidArgumentError(absl::StrCat(where, ": ", cam.model, " takes ", m->num_params,
                                                   " parameters, got ", cam.params.size()));
  }
  if (cam.width <= 0 || cam.height <= 0 || cam.width > 65536 || cam.height > 65536) {
    return absl::InvalidArgumentError(absl::StrCat(where, ": bad image size ", cam.width, "x", cam.height));
  }
  for (double p : cam.params) {
    if (!std::isfinite(p)) return absl::InvalidArgumentError(absl::StrCat(where, ": non-finite parameter"));
  }
  if (!(cam.params[0] > 0)) return absl::InvalidArgumentError(absl::StrCat(where, ": focal length must be positive"));
  return absl::OkStatus();
}

absl::Status ValidateImagePose(const ColmapImage& im, const double* q, const std::string& where) {
  for (int i = 0; i < 4; ++i) {
    if (!std::isfinite(q[i])) return absl::InvalidArgumentError(absl::StrCat(where, ": non-finite quaternion"));
  }
  if (!im.t_cam_from_world.allFinite()) return absl::InvalidArgumentError(absl::StrCat(where, ": non-finite translation"));
  const double norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  if (std::abs(norm - 1) > 1e-3) {
    return absl::InvalidArgumentError(absl::StrCat(where, ": quaternion norm ", norm, " is not 1"));
  }
  return absl::OkStatus();
}

absl::Status CheckReferences(const ColmapModel& model, const std::string& images_file) {
  for (const ColmapImage& im : model.images) {
    if (!model.cameras.count(im.camera_id)) {
      return absl::InvalidArgumentError(absl::StrCat(images_file, ": image ", im.id, " (", im.name,
                                                     ") refers to camera ", im.camera_id, ", not in the cameras file"));
    }
  }
  if (model.images.empty()) return absl::InvalidArgumentError(absl::StrCat(images_file, ": no images"));
  return absl::OkStatus();
}

// Bounds-checked little-endian reader over a whole file.
class BinaryReader {
 public:
  BinaryReader(std::string bytes, std::string path) : bytes_(std::move(bytes)), path_(std::move(path)) {}
  template <typename T>
  absl::Status Read(T* value) {
    if (pos_ + sizeof(T) > bytes_.size()) return Truncated();
    std::memcpy(value, bytes_.data() + pos_, sizeof(T));
    pos_ += sizeof(T);
    return absl::OkStatus();
  }
  absl::Status ReadString(std::string* s) {
    const size_t end = bytes_.find('\0', pos_);
    if (end == std::string::npos) return Truncated();
    *s = bytes_.substr(pos_, end - pos_);
    pos_ = end + 1;
    return absl::OkStatus();
  }
  absl::Status Skip(uint64_t n) {
    if (n > bytes_.size() - pos_) return Truncated();
    pos_ += n;
    return absl::OkStatus();
  }
  absl::Status CheckCount(uint64_t count, uint64_t min_bytes_each) {
    if (min_bytes_each > 0 && count > (bytes_.size() - pos_) / min_bytes_each) {
      return absl::InvalidArgumentError(absl::StrCat(path_, ": count ", count, " at byte ", pos_,
                                                     " does not fit the file (truncated or corrupt)"));
    }
    return absl::OkStatus();
  }
  size_t pos() const { return pos_; }
  const std::string& path() const { return path_; }
  bool AtEnd() const { return pos_ == bytes_.size(); }

 private:
  absl::Status Truncated() const {
    return absl::DataLossError(absl::StrCat(path_, ": truncated at byte ", pos_, " of ", bytes_.size()));
  }
  std::string bytes_;
  std::string path_;
  size_t pos_ = 0;
};

#define COLMAP_RETURN_IF_ERROR(expr)     \
  do {                                   \
    if (absl::Status _s = (expr); !_s.ok()) return _s; \
  } while (0)

absl::Status WriteBytesAtomically(const std::string& path, const std::string& bytes) {
  const fs::path target(path);
  const fs::path tmp = target.parent_path() / absl::StrCat(".", target.filename().string(), ".tmp", getpid());
  {
    std::ofstream out(tmp, std::ios::binary);
    if (!out || !out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()))) {
      return absl::PermissionDeniedError(absl::StrCat(path, ": cannot write"));
    }
  }
  std::error_code ec;
  fs::rename(tmp, target, ec);
  if (ec) return absl::PermissionDeniedError(absl::StrCat(path, ": cannot rename into place"));
  return absl::OkStatus();
}

// Fraction of sampled model points that project into a frame's image onto a pixel of about their
// own colour (summed absolute RGB difference under 60), over a few frames; `transposed` reads each
// rotation as its transpose. Points that miss the image count against the reading too: photos
// are taken of the reconstructed scene, so a right reading puts most of it in view.
double ColourAgreement(const DriveLog& log, bool transposed) {
  double sum = 0;
  int n = 0;
  const size_t step = std::max<size_t>(1, log.frames.size() / 4);
  for (size_t f = 0; f < log.frames.size(); f += step) {
    const CameraObservation& obs = log.frames[f].cameras[0];
    absl::StatusOr<cv::Mat> image = LoadImageRgb(obs.path);
    if (!image.ok()) continue;
    const CameraIntrinsics& k = log.cameras[obs.camera].intrinsics;
    Eigen::Isometry3d t = log.frames[f].T_world_from_ego.inverse();
    if (transposed) t.linear().transposeInPlace();
    const size_t pstep = std::max<size_t>(1, log.sparse_points.size() / 3000);
    for (size_t i = 0; i < log.sparse_points.size(); i += pstep) {
      const Eigen::Vector3d p = t * log.sparse_points[i];
      ++n;
      if (p.z() <= 0) continue;
      const long u = std::lround(k.fx * p.x() / p.z() + k.cx), v = std::lround(k.fy * p.y() / p.z() + k.cy);
      if (u < 0 || v < 0 || u >= image->cols || v >= image->rows) continue;
      const cv::Vec3b px = image->at<cv::Vec3b>(static_cast<int>(v), static_cast<int>(u));
      int diff = 0;
      for (int c = 0; c < 3; ++c) diff += std::abs(int(px[c]) - int(log.sparse_colours[i][c]));
      sum += diff < 60 ? 1 : 0;
    }
  }
  return n > 100 ? sum / n : -1;
}

template <typename T>
void Put(std::string* out, T v) {
  out->append(reinterpret_cast<const char*>(&v), sizeof(T));
}

}  // namespace

Eigen::Isometry3d ColmapImage::T_cam_from_world() const {
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  t.linear() = q_cam_from_world.normalized().toRotationMatrix();
  t.translation() = t_cam_from_world;
  return t;
}

absl::StatusOr<ColmapModel> ReadColmapText(const std::string& model_dir) {
  const fs::path dir(model_dir);
  ColmapModel model;
  const std::string cameras_path = (dir / "cameras.txt").string();
  absl::StatusOr<std::vector<std::string>> lines = ReadLines(cameras_path);
  if (!lines.ok()) return lines.status();
  for (size_t i = 0; i < lines->size(); ++i) {
    if (IsBlankOrComment((*lines)[i])) continue;
    const std::string where = absl::StrCat(cameras_path, ": line ", i + 1);
    const std::vector<std::string> tok = Tokens((*lines)[i]);
    if (tok.size() < 4) return absl::InvalidArgumentError(absl::StrCat(where, ": expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]"));
    std::string rest;
    for (size_t t = 4; t < tok.size(); ++t) absl::StrAppend(&rest, tok[t], " ");
    absl::StatusOr<std::vector<double>> head = ParseNumbers(absl::StrCat(tok[0], " ", tok[2], " ", tok[3]), cameras_path, static_cast<int>(i + 1), 3);
    if (!head.ok()) return head.status();
    absl::StatusOr<std::vector<double>> params = ParseNumbers(rest, cameras_path, static_cast<int>(i + 1));
    if (!params.ok()) return params.status();
    ColmapCamera cam;
    cam.id = static_cast<uint32_t>((*head)[0]);
    cam.model = tok[1];
    cam.width = static_cast<int>((*head)[1]);
    cam.height = static_cast<int>((*head)[2]);
    cam.params = *params;
    COLMAP_RETURN_IF_ERROR(ValidateCamera(cam, where));
    if (!model.cameras.emplace(cam.id, cam).second) {
      return absl::InvalidArgumentError(absl::StrCat(where, ": camera ", cam.id, " defined twice"));
    }
  }
  if (model.cameras.empty()) return absl::InvalidArgumentError(absl::StrCat(cameras_path, ": no cameras"));

  const std::string images_path = (dir / "images.txt").string();
  lines = ReadLines(images_path);
  if (!lines.ok()) return lines.status();
  bool expect_image = true;  // images.txt alternates an image line and its POINTS2D line
  for (size_t i = 0; i < lines->size(); ++i) {
    const std::string& line = (*lines)[i];
    if (!line.empty() && line[0] == '#') continue;
    const std::string where = absl::StrCat(images_path, ": line ", i + 1);
    if (!expect_image) {
      expect_image = true;
      const std::vector<std::string> tok = Tokens(line);
      if (tok.size() % 3 != 0) {
        return absl::InvalidArgumentError(absl::StrCat(where, ": POINTS2D needs X Y POINT3D_ID triples, got ", tok.size(), " values"));
      }
      continue;
    }
    if (IsBlankOrComment(line)) continue;
    expect_image = false;
    const std::vector<std::string> tok = Tokens(line);
    if (tok.size() < 10) return absl::InvalidArgumentError(absl::StrCat(where, ": expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, got ", tok.size(), " fields"));
    std::string nums;
    for (int t = 0; t < 9; ++t) absl::StrAppend(&nums, tok[t], " ");
    absl::StatusOr<std::vector<double>> v = ParseNumbers(nums, images_path, static_cast<int>(i + 1), 9);
    if (!v.ok()) return v.status();
    ColmapImage im;
    im.id = static_cast<uint32_t>((*v)[0]);
    const double q[4] = {(*v)[1], (*v)[2], (*v)[3], (*v)[4]};
    im.q_cam_from_world = Eigen::Quaterniond(q[0], q[1], q[2], q[3]);
    im.t_cam_from_world = Eigen::Vector3d((*v)[5], (*v)[6], (*v)[7]);
    im.camera_id = static_cast<uint32_t>((*v)[8]);
    im.name = tok[9];
    for (size_t t = 10; t < tok.size(); ++t) absl::StrAppend(&im.name, " ", tok[t]);
    COLMAP_RETURN_IF_ERROR(ValidateImagePose(im, q, where));
    model.images.push_back(std::move(im));
  }
  COLMAP_RETURN_IF_ERROR(CheckReferences(model, images_path));

  const std::string points_path = (dir / "points3D.txt").string();
  if (fs::exists(points_path)) {
    lines = ReadLines(points_path);
    if (!lines.ok()) return lines.status();
    for (size_t i = 0; i < lines->size(); ++i) {
      if (IsBlankOrComment((*lines)[i])) continue;
      const std::vector<std::string> tok = Tokens((*lines)[i]);
      const std::string where = absl::StrCat(points_path, ": line ", i + 1);
      if (tok.size() < 8 || (tok.size() - 8) % 2 != 0) {
        return absl::InvalidArgumentError(absl::StrCat(where, ": expected POINT3D_ID X Y Z R G B ERROR TRACK[], got ", tok.size(), " fields"));
      }
      std::string nums;
      for (int t = 0; t < 8; ++t) absl::StrAppend(&nums, tok[t], " ");
      absl::StatusOr<std::vector<double>> v = ParseNumbers(nums, points_path, static_cast<int>(i + 1), 8);
      if (!v.ok()) return v.status();
      ColmapPoint p;
      p.id = static_cast<uint64_t>((*v)[0]);
      p.xyz = Eigen::Vector3d((*v)[1], (*v)[2], (*v)[3]);
      if (!p.xyz.allFinite()) return absl::InvalidArgumentError(absl::StrCat(where, ": non-finite position"));
      for (int c = 0; c < 3; ++c) {
        const double x = (*v)[4 + c];
        if (!(x >= 0 && x <= 255)) return absl::InvalidArgumentError(absl::StrCat(where, ": colour outside 0..255"));
        p.rgb[c] = static_cast<uint8_t>(x);
      }
      p.error = (*v)[7];
      model.points.push_back(p);
    }
  }
  return model;
}

absl::StatusOr<ColmapModel> ReadColmapBinary(const std::string& model_dir) {
  const fs::path dir(model_dir);
  ColmapModel model;
  {
    const std::string path = (dir / "cameras.bin").string();
    absl::StatusOr<std::string> bytes = ReadTextFile(path);
    if (!bytes.ok()) return bytes.status();
    BinaryReader r(*std::move(bytes), path);
    uint64_t n;
    COLMAP_RETURN_IF_ERROR(r.Read(&n));
    COLMAP_RETURN_IF_ERROR(r.CheckCount(n, 24));
    for (uint64_t i = 0; i < n; ++i) {
      const std::string where = absl::StrCat(path, ": camera record ", i, " at byte ", r.pos());
      uint32_t id = 0;
      int32_t model_id = 0;
      uint64_t w = 0, h = 0;
      COLMAP_RETURN_IF_ERROR(r.Read(&id));
      COLMAP_RETURN_IF_ERROR(r.Read(&model_id));
      COLMAP_RETURN_IF_ERROR(r.Read(&w));
      COLMAP_RETURN_IF_ERROR(r.Read(&h));
      const ModelInfo* m = ModelById(model_id);
      if (m == nullptr) return absl::InvalidArgumentError(absl::StrCat(where, ": camera model id ", model_id, " not supported"));
      ColmapCamera cam{id, m->name, static_cast<int>(std::min<uint64_t>(w, 1 << 30)),
                       static_cast<int>(std::min<uint64_t>(h, 1 << 30)), std::vector<double>(m->num_params)};
      for (double& p : cam.params) COLMAP_RETURN_IF_ERROR(r.Read(&p));
      COLMAP_RETURN_IF_ERROR(ValidateCamera(cam, where));
      model.cameras[id] = cam;
    }
    if (!r.AtEnd()) return absl::InvalidArgumentError(absl::StrCat(path, ": trailing bytes after ", n, " cameras"));
  }
  {
    const std::string path = (dir / "images.bin").string();
    absl::StatusOr<std::string> bytes = ReadTextFile(path);
    if (!bytes.ok()) return bytes.status();
    BinaryReader r(*std::move(bytes), path);
    uint64_t n;
    COLMAP_RETURN_IF_ERROR(r.Read(&n));
    COLMAP_RETURN_IF_ERROR(r.CheckCount(n, 4 + 56 + 4 + 1 + 8));
    for (uint64_t i = 0; i < n; ++i) {
      const std::string where = absl::StrCat(path, ": image record ", i, " at byte ", r.pos());
      ColmapImage im;
      double q[4], t[3];
      COLMAP_RETURN_IF_ERROR(r.Read(&im.id));
      for (double& x : q) COLMAP_RETURN_IF_ERROR(r.Read(&x));
      for (double& x : t) COLMAP_RETURN_IF_ERROR(r.Read(&x));
      COLMAP_RETURN_IF_ERROR(r.Read(&im.camera_id));
      COLMAP_RETURN_IF_ERROR(r.ReadString(&im.name));
      uint64_t num_points2d;
      COLMAP_RETURN_IF_ERROR(r.Read(&num_points2d));
      COLMAP_RETURN_IF_ERROR(r.CheckCount(num_points2d, 24));
      COLMAP_RETURN_IF_ERROR(r.Skip(num_points2d * 24));
      im.q_cam_from_world = Eigen::Quaterniond(q[0], q[1], q[2], q[3]);
      im.t_cam_from_world = Eigen::Vector3d(t[0], t[1], t[2]);
      COLMAP_RETURN_IF_ERROR(ValidateImagePose(im, q, where));
      model.images.push_back(std::move(im));
    }
    if (!r.AtEnd()) return absl::InvalidArgumentError(absl::StrCat(path, ": trailing bytes after ", n, " images"));
    COLMAP_RETURN_IF_ERROR(CheckReferences(model, path));
  }
  const std::string path = (dir / "points3D.bin").string();
  if (fs::exists(path)) {
    absl::StatusOr<std::string> bytes = ReadTextFile(path);
    if (!bytes.ok()) return bytes.status();
    BinaryReader r(*std::move(bytes), path);
    uint64_t n;
    COLMAP_RETURN_IF_ERROR(r.Read(&n));
    COLMAP_RETURN_IF_ERROR(r.CheckCount(n, 8 + 24 + 3 + 8 + 8));
    model.points.reserve(n);
    for (uint64_t i = 0; i < n; ++i) {
      ColmapPoint p;
      uint64_t track;
      COLMAP_RETURN_IF_ERROR(r.Read(&p.id));
      for (int c = 0; c < 3; ++c) COLMAP_RETURN_IF_ERROR(r.Read(&p.xyz[c]));
      for (int c = 0; c < 3; ++c) COLMAP_RETURN_IF_ERROR(r.Read(&p.rgb[c]));
      COLMAP_RETURN_IF_ERROR(r.Read(&p.error));
      COLMAP_RETURN_IF_ERROR(r.Read(&track));
      COLMAP_RETURN_IF_ERROR(r.CheckCount(track, 8));
      COLMAP_RETURN_IF_ERROR(r.Skip(track * 8));
      if (!p.xyz.allFinite()) {
        return absl::InvalidArgumentError(absl::StrCat(path, ": point ", p.id, ": non-finite position"));
      }
      model.points.push_back(p);
    }
    if (!r.AtEnd()) return absl::InvalidArgumentError(absl::StrCat(path, ": trailing bytes after ", n, " points"));
  }
  return model;
}

absl::StatusOr<ColmapModel> ReadColmapModel(const std::string& model_dir) {
  if (fs::exists(fs::path(model_dir) / "cameras.bin")) return ReadColmapBinary(model_dir);
  return ReadColmapText(model_dir);
}

absl::Status WriteColmapBinary(const ColmapModel& model, const std::string& model_dir) {
  std::error_code ec;
  if (!fs::is_directory(model_dir, ec)) return absl::NotFoundError(absl::StrCat(model_dir, ": no such directory"));
  std::string cams;
  Put<uint64_t>(&cams, model.cameras.size());
  for (const auto& [id, cam] : model.cameras) {
    const ModelInfo* m = ModelByName(cam.model);
    if (m == nullptr) return absl::InvalidArgumentError(absl::StrCat("camera model ", cam.model, " not supported"));
    Put<uint32_t>(&cams, id);
    Put<int32_t>(&cams, m->id);
    Put<uint64_t>(&cams, cam.width);
    Put<uint64_t>(&cams, cam.height);
    for (double p : cam.params) Put<double>(&cams, p);
  }
  std::string imgs;
  Put<uint64_t>(&imgs, model.images.size());
  for (const ColmapImage& im : model.images) {
    Put<uint32_t>(&imgs, im.id);
    const Eigen::Quaterniond& q = im.q_cam_from_world;
    for (double x : {q.w(), q.x(), q.y(), q.z()}) Put<double>(&imgs, x);
    for (int c = 0; c < 3; ++c) Put<double>(&imgs, im.t_cam_from_world[c]);
    Put<uint32_t>(&imgs, im.camera_id);
    imgs.append(im.name);
    imgs.push_back('\0');
    Put<uint64_t>(&imgs, 0);
  }
  std::string pts;
  Put<uint64_t>(&pts, model.points.size());
  for (const ColmapPoint& p : model.points) {
    Put<uint64_t>(&pts, p.id);
    for (int c = 0; c < 3; ++c) Put<double>(&pts, p.xyz[c]);
    for (int c = 0; c < 3; ++c) Put<uint8_t>(&pts, p.rgb[c]);
    Put<double>(&pts, p.error);
    Put<uint64_t>(&pts, 0);
  }
  const fs::path dir(model_dir);
  COLMAP_RETURN_IF_ERROR(WriteBytesAtomically((dir / "cameras.bin").string(), cams));
  COLMAP_RETURN_IF_ERROR(WriteBytesAtomically((dir / "images.bin").string(), imgs));
  return WriteBytesAtomically((dir / "points3D.bin").string(), pts);
}

absl::StatusOr<CameraIntrinsics> ColmapIntrinsics(const ColmapCamera& cam) {
  COLMAP_RETURN_IF_ERROR(ValidateCamera(cam, absl::StrCat("camera ", cam.id)));
  CameraIntrinsics k;
  k.width = cam.width;
  k.height = cam.height;
  const std::vector<double>& p = cam.params;
  if (cam.model == "SIMPLE_PINHOLE" || cam.model == "SIMPLE_RADIAL" || cam.model == "RADIAL") {
    k.fx = k.fy = p[0];
    k.cx = p[1];
    k.cy = p[2];
    if (cam.model == "SIMPLE_RADIAL") {
      k.model = DistortionModel::kSimpleRadial;
      k.distortion = {p[3]};
    } else if (cam.model == "RADIAL") {
      k.model = DistortionModel::kRadial;
      k.distortion = {p[3], p[4]};
    }
  } else {  // PINHOLE, OPENCV
    k.fx = p[0];
    k.fy = p[1];
    k.cx = p[2];
    k.cy = p[3];
    if (cam.model == "OPENCV") {
      k.model = DistortionModel::kOpenCv;
      k.distortion = {p[4], p[5], p[6], p[7]};
    }
  }
  k.cx -= 0.5;  // COLMAP: pixel (0, 0) spans [0, 1); OpenCV: its centre is 0
  k.cy -= 0.5;
  return k;
}

absl::StatusOr<DriveLog> ReadColmapLog(const std::string& model_dir, const std::string& images_dir) {
  absl::StatusOr<ColmapModel> model = ReadColmapModel(model_dir);
  if (!model.ok()) return model.status();
  DriveLog log;
  log.format = "colmap";
  log.root = model_dir;
  log.pose_source = kColmapPoseSource;
  std::map<uint32_t, int> slot;
  for (const auto& [id, cam] : model->cameras) {
    absl::StatusOr<CameraIntrinsics> k = ColmapIntrinsics(cam);
    if (!k.ok()) return k.status();
    slot[id] = static_cast<int>(log.cameras.size());
    log.cameras.push_back({absl::StrCat("colmap_camera_", id), *k, Eigen::Isometry3d::Identity(), true});
  }
  std::vector<const ColmapImage*> order;
  for (const ColmapImage& im : model->images) order.push_back(&im);
  std::sort(order.begin(), order.end(), [](const ColmapImage* a, const ColmapImage* b) { return a->name < b->name; });
  std::vector<bool> size_checked(log.cameras.size(), false);
  for (size_t i = 0; i < order.size(); ++i) {
    const ColmapImage& im = *order[i];
    const std::string path = (fs::path(images_dir) / im.name).string();
    if (!fs::is_regular_file(path)) {
      log.problems.push_back(absl::StrCat(path, ": image ", im.id, " missing; frame skipped"));
      continue;
    }
    const int cam = slot.at(im.camera_id);
    if (!size_checked[cam]) {
      // The model must describe these files (a model of images/ read with images_4/ would not).
      cv::Mat probe;
      try {
        probe = cv::imread(path, cv::IMREAD_UNCHANGED);
      } catch (const cv::Exception&) {
      }
      if (probe.empty()) return absl::DataLossError(absl::StrCat(path, ": cannot decode image"));
      const CameraIntrinsics& k = log.cameras[cam].intrinsics;
      if (probe.cols != k.width || probe.rows != k.height) {
        return absl::InvalidArgumentError(absl::StrCat(path, ": image is ", probe.cols, "x", probe.rows,
                                                       " but camera ", im.camera_id, " in ", model_dir,
                                                       " is ", k.width, "x", k.height));
      }
      size_checked[cam] = true;
    }
    Frame frame;
    frame.source_index = static_cast<int>(im.id);
    frame.time_us = static_cast<int64_t>(log.frames.size()) * kAssumedFrameUs;
    frame.T_world_from_ego = im.T_cam_from_world().inverse();
    frame.cameras.push_back({cam, frame.time_us, path});
    log.frames.push_back(std::move(frame));
  }
  if (log.frames.empty()) return absl::NotFoundError(absl::StrCat(images_dir, ": none of the model's images found"));
  log.problems.push_back("COLMAP model: no timestamps; frames in image-name order, 10 Hz assumed");
  for (const ColmapPoint& p : model->points) {
    log.sparse_points.push_back(p.xyz);
    log.sparse_colours.push_back(p.rgb);
  }
  // Some exporters (3DGS cameras.json -> images.txt) write the camera-to-world rotation as qvec next
  // to a world-to-camera tvec. The coloured points tell the two apart: under the right reading they
  // land on pixels of their own colour.
  if (!log.sparse_points.empty()) {
    const double standard = ColourAgreement(log, false);
    const double transposed = ColourAgreement(log, true);
    if (standard >= 0 && transposed > 2 * standard + 0.02) {
      for (Frame& f : log.frames) {
        Eigen::Isometry3d t = f.T_world_from_ego.inverse();
        t.linear().transposeInPlace();
        f.T_world_from_ego = t.inverse();
      }
      log.problems.push_back(absl::StrCat(
          model_dir, ": image rotations are transposed (qvec is camera-to-world, tvec world-to-camera): "
          "points3D land in view on pixels of their colour ", static_cast<int>(std::lround(100 * standard)),
          "% of the time as written, ", static_cast<int>(std::lround(100 * transposed)),
          "% transposed; read transposed"));
    }
  }
  return log;
}

absl::StatusOr<DriveLog> ReadColmapProject(const std::string& root_dir) {
  const fs::path root(root_dir);
  const auto is_model = [](const fs::path& d) {
    return fs::exists(d / "cameras.txt") || fs::exists(d / "cameras.bin");
  };
  fs::path model;
  if (is_model(root)) {
    model = root;
  } else if (is_model(root / "sparse" / "0")) {
    model = root / "sparse" / "0";
  } else if (is_model(root / "sparse")) {
    model = root / "sparse";
  } else {
    std::vector<fs::path> candidates;
    std::error_code ec;
    for (const auto& e : fs::directory_iterator(root, ec)) {
      if (e.is_directory() && absl::StartsWith(e.path().filename().string(), "sparse") && is_model(e.path())) {
        candidates.push_back(e.path());
      }
    }
    std::sort(candidates.begin(), candidates.end());
    if (candidates.empty()) return absl::NotFoundError(absl::StrCat(root_dir, ": no COLMAP model (cameras.txt/.bin)"));
    model = candidates.front();
  }
  // The image folder: images_N for a model named *_images_N, else images/, else the model's parent.
  const fs::path base = model == root ? root.parent_path() : root;
  std::vector<fs::path> image_dirs;
  const std::string model_name = model.filename().string();
  if (const size_t at = model_name.find("images"); at != std::string::npos) {
    image_dirs.push_back(base / model_name.substr(at));
  }
  image_dirs.push_back(base / "images");
  image_dirs.push_back(base);
  for (const fs::path& d : image_dirs) {
    if (fs::is_directory(d) && d != model) {
      absl::StatusOr<DriveLog> log = ReadColmapLog(model.string(), d.string());
      if (log.ok() || d == image_dirs.back()) {
        if (log.ok()) log->root = root_dir;
        return log;
      }
      if (!absl::IsNotFound(log.status())) return log.status();
    }
  }
  return absl::NotFoundError(absl::StrCat(root_dir, ": no image folder for model ", model.string()));
}

}  // namespace streetsim
