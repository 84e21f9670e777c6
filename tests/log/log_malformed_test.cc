// Malformed copies of the shared logs (made in a temp dir): every reader names the file and line,
// or reports and skips the frame.
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <iterator>
#include <fstream>
#include <sstream>

#include "gtest/gtest.h"
#include "scene/log/colmap_reader.h"
#include "scene/log/kitti_raw_reader.h"
#include "scene/log/open_log.h"
#include "scene/log/oxts.h"
#include "scene/log/poses_file.h"

namespace streetsim {
namespace {

namespace fs = std::filesystem;
const std::string kData = STREETSIM_DATA_DIR;
const fs::path kRawDay = kData + "/kitti_raw/2011_09_26";
const fs::path kRawDrive = kRawDay / "2011_09_26_drive_sfnd_sync";
const fs::path kOxts = kData + "/kitti_oxts/2011_09_26/2011_09_26_drive_0013_sync/oxts";

std::string Slurp(const fs::path& p) {
  std::ifstream in(p);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}
void Write(const fs::path& p, const std::string& text) {
  fs::remove(p);  // may be a symlink into the shared data: never write through it
  std::ofstream(p) << text;
}
// Replaces the first occurrence of `from` in the file.
void Edit(const fs::path& p, const std::string& from, const std::string& to) {
  std::string text = Slurp(p);
  const size_t at = text.find(from);
  ASSERT_NE(at, std::string::npos) << from;
  text.replace(at, from.size(), to);
  Write(p, text);
}
bool Mentions(const DriveLog& log, const std::string& text) {
  for (const std::string& p : log.problems) {
    if (p.find(text) != std::string::npos) return true;
  }
  return false;
}
::testing::AssertionResult ErrorSays(const absl::Status& s, const std::string& a, const std::string& b = "") {
  if (s.ok()) return ::testing::AssertionFailure() << "expected an error";
  const std::string m(s.message());
  if (m.find(a) == std::string::npos || m.find(b) == std::string::npos) {
    return ::testing::AssertionFailure() << "error '" << m << "' lacks '" << a << "' / '" << b << "'";
  }
  return ::testing::AssertionSuccess();
}

class Malformed : public testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::path(testing::TempDir()) / ("malformed_" + std::to_string(getpid()) + "_" + std::string(testing::UnitTest::GetInstance()->current_test_info()->name()));
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  // Every run gets its own pid-named directory, so leaving it would fill /tmp run after run.
  void TearDown() override {
    std::error_code ec;
    fs::remove_all(dir_, ec);
  }
  // A copy of the oxts folder (small text files).
  fs::path CopyOxts() {
    const fs::path drive = dir_ / "drive";
    fs::create_directories(drive);
    fs::copy(kOxts, drive / "oxts", fs::copy_options::recursive);
    return drive;
  }
  // A 6-frame KITTI raw drive: calib copies, images/scans as symlinks into the shared data.
  fs::path MakeRawDrive(int frames = 6) {
    const fs::path day = dir_ / "2011_09_26";
    const fs::path drive = day / "2011_09_26_drive_sfnd_sync";
    fs::create_directories(drive / "image_02" / "data");
    fs::create_directories(drive / "velodyne_points" / "data");
    for (const char* f : {"calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt"}) {
      fs::copy(kRawDay / f, day / f);
    }
    char name[32];
    for (int i = 0; i < frames; ++i) {
      std::snprintf(name, sizeof(name), "%010d", i);
      fs::create_symlink(kRawDrive / "image_02" / "data" / (std::string(name) + ".png"),
                         drive / "image_02" / "data" / (std::string(name) + ".png"));
      fs::create_symlink(kRawDrive / "velodyne_points" / "data" / (std::string(name) + ".bin"),
                         drive / "velodyne_points" / "data" / (std::string(name) + ".bin"));
    }
    std::istringstream all(Slurp(kRawDrive / "poses_velo_icp_estimated.txt"));
    std::string line, poses;
    for (int i = 0; i <= frames && std::getline(all, line); ++i) poses += line + "\n";  // + comment
    Write(drive / "poses_velo_icp_estimated.txt", poses);
    return drive;
  }
  fs::path dir_;
};

TEST_F(Malformed, OxtsRecordWithTooFewValuesNamesFileAndLine) {
  const fs::path drive = CopyOxts();
  const fs::path rec = drive / "oxts" / "data" / "0000000012.txt";
  std::string text = Slurp(rec);
  text = text.substr(0, text.rfind(' '));  // drop the last value
  Write(rec, text);
  EXPECT_TRUE(ErrorSays(OpenLog(drive.string()).status(), "0000000012.txt: line 1: expected 30 values, got 29"));
}

TEST_F(Malformed, OxtsRecordWithGarbageNamesTheToken) {
  const fs::path drive = CopyOxts();
  Edit(drive / "oxts" / "data" / "0000000003.txt", " ", " 12x4 ");
  EXPECT_TRUE(ErrorSays(OpenLog(drive.string()).status(), "0000000003.txt: line 1", "'12x4' is not a number"));
}

TEST_F(Malformed, OxtsNanPositionIsBridgedNotReturned) {
  const fs::path drive = CopyOxts();
  const fs::path rec = drive / "oxts" / "data" / "0000000005.txt";
  std::string text = Slurp(rec);
  Write(rec, "nan nan" + text.substr(text.find(' ', text.find(' ') + 1)));
  absl::StatusOr<DriveLog> log = OpenLog(drive.string());
  ASSERT_TRUE(log.ok()) << log.status();
  EXPECT_EQ(log->frames.size(), 144u);
  EXPECT_TRUE(log->frames[5].T_world_from_ego.matrix().allFinite());
  EXPECT_TRUE(Mentions(*log, "oxts records 5-5: no valid position"));
}

TEST_F(Malformed, OxtsNanOrientationIsInterpolated) {
  const fs::path drive = CopyOxts();
  const fs::path rec = drive / "oxts" / "data" / "0000000007.txt";
  std::istringstream in(Slurp(rec));
  std::vector<std::string> v((std::istream_iterator<std::string>(in)), std::istream_iterator<std::string>());
  v[5] = "NaN";  // yaw
  std::string text;
  for (const std::string& s : v) text += s + " ";
  Write(rec, text);
  absl::StatusOr<DriveLog> log = OpenLog(drive.string());
  ASSERT_TRUE(log.ok()) << log.status();
  EXPECT_TRUE(log->frames[7].T_world_from_ego.matrix().allFinite());
  EXPECT_TRUE(Mentions(*log, "non-finite roll/pitch/yaw"));
}

TEST_F(Malformed, MissingTimestampsAssumeTenHertz) {
  const fs::path drive = CopyOxts();
  fs::remove(drive / "oxts" / "timestamps.txt");
  absl::StatusOr<DriveLog> log = OpenLog(drive.string());
  ASSERT_TRUE(log.ok()) << log.status();
  EXPECT_FALSE(log->time_is_absolute);
  EXPECT_EQ(log->frames[3].time_us, 300'000);
  EXPECT_TRUE(Mentions(*log, "timestamps.txt: missing; 10 Hz assumed"));
}

TEST_F(Malformed, ShortTimestampsSkipTheUntimedRecords) {
  const fs::path drive = CopyOxts();
  std::string ts = Slurp(drive / "oxts" / "timestamps.txt");
  for (int i = 0; i < 4; ++i) ts = ts.substr(0, ts.rfind('\n', ts.size() - 2) + 1);
  Write(drive / "oxts" / "timestamps.txt", ts);
  absl::StatusOr<DriveLog> log = OpenLog(drive.string());
  ASSERT_TRUE(log.ok()) << log.status();
  EXPECT_EQ(log->frames.size(), 140u);
  EXPECT_TRUE(Mentions(*log, "140 timestamps for 144 oxts records; 4 records without a time skipped"));
}

TEST_F(Malformed, BadTimestampNamesTheLine) {
  const fs::path drive = CopyOxts();
  Edit(drive / "oxts" / "timestamps.txt", "13:10:51.275615407", "13:70:51.275615407");
  EXPECT_TRUE(ErrorSays(OpenLog(drive.string()).status(), "timestamps.txt: line 2"));
}

TEST_F(Malformed, RawCopyReadsCleanly) {
  absl::StatusOr<DriveLog> log = OpenLog(MakeRawDrive().string());
  ASSERT_TRUE(log.ok()) << log.status();
  EXPECT_EQ(log->frames.size(), 6u);
}

TEST_F(Malformed, RawMissingCalibrationLine) {
  const fs::path drive = MakeRawDrive();
  std::string text = Slurp(drive.parent_path() / "calib_cam_to_cam.txt");
  const size_t at = text.find("P_rect_02");
  text.erase(at, text.find('\n', at) - at + 1);
  Write(drive.parent_path() / "calib_cam_to_cam.txt", text);
  EXPECT_TRUE(ErrorSays(OpenLog(drive.string()).status(), "calib_cam_to_cam.txt", "missing calibration entry 'P_rect_02'"));
}

TEST_F(Malformed, RawCalibrationWithTooFewValues) {
  const fs::path drive = MakeRawDrive();
  Edit(drive.parent_path() / "calib_velo_to_cam.txt", " -2.717806e-01", "");
  EXPECT_TRUE(ErrorSays(OpenLog(drive.string()).status(), "calib_velo_to_cam.txt: line 3", "T: expected 3 values, got 2"));
}

TEST_F(Malformed, RawCalibrationRotationThatIsNotARotation) {
  const fs::path drive = MakeRawDrive();
  Edit(drive.parent_path() / "calib_imu_to_velo.txt", "R: 9.999976e-01", "R: 1.999976e+00");
  EXPECT_TRUE(ErrorSays(OpenLog(drive.string()).status(), "calib_imu_to_velo.txt: line 2", "not a rotation matrix"));
}

TEST_F(Malformed, RawCalibrationOfTheWrongImageSize) {
  const fs::path drive = MakeRawDrive();
  Edit(drive.parent_path() / "calib_cam_to_cam.txt", "S_rect_02: 1.242000e+03", "S_rect_02: 1.392000e+03");
  EXPECT_TRUE(ErrorSays(OpenLog(drive.string()).status(), "0000000000.png: image is 1242x375", "S_rect_02"));
}

TEST_F(Malformed, RawMismatchedCountsAreReportedAndFramesKept) {
  const fs::path drive = MakeRawDrive();
  fs::remove(drive / "image_02" / "data" / "0000000004.png");
  absl::StatusOr<DriveLog> log = OpenLog(drive.string());
  ASSERT_TRUE(log.ok()) << log.status();
  EXPECT_TRUE(Mentions(*log, "image_02: 5 images for 6 frames"));
  EXPECT_EQ(log->frames.size(), 6u);
  EXPECT_TRUE(log->frames[4].cameras.empty());
  EXPECT_EQ(log->frames[4].lidars.size(), 1u);
}

TEST_F(Malformed, RawShortPosesFileSkipsUnposedFrames) {
  const fs::path drive = MakeRawDrive();
  std::string poses = Slurp(drive / "poses_velo_icp_estimated.txt");
  poses = poses.substr(0, poses.rfind('\n', poses.size() - 2) + 1);
  Write(drive / "poses_velo_icp_estimated.txt", poses);
  absl::StatusOr<DriveLog> log = OpenLog(drive.string());
  ASSERT_TRUE(log.ok()) << log.status();
  EXPECT_EQ(log->frames.size(), 5u);
  EXPECT_TRUE(Mentions(*log, "5 poses for 6 frames"));
  EXPECT_TRUE(Mentions(*log, "1 frames without a pose skipped (first: 5)"));
}

TEST_F(Malformed, RawNanPoseNamesTheLine) {
  const fs::path drive = MakeRawDrive();
  Edit(drive / "poses_velo_icp_estimated.txt", "0.089341803", "nan");
  EXPECT_TRUE(ErrorSays(OpenLog(drive.string()).status(), "poses_velo_icp_estimated.txt: line 3", "non-finite"));
}

TEST_F(Malformed, TruncatedVelodyneScanNamesTheFile) {
  const fs::path drive = MakeRawDrive();
  const fs::path scan = drive / "velodyne_points" / "data" / "0000000002.bin";
  fs::remove(scan);
  fs::copy_file(kRawDrive / "velodyne_points" / "data" / "0000000002.bin", scan);
  fs::resize_file(scan, fs::file_size(scan) - 7);
  absl::StatusOr<DriveLog> log = OpenLog(drive.string());
  ASSERT_TRUE(log.ok()) << log.status();  // scans load lazily
  EXPECT_TRUE(ErrorSays(LoadLidarScan(log->frames[2].lidars[0].path).status(), "0000000002.bin",
                        "not a whole number of 16-byte points"));
}

TEST_F(Malformed, OdometryShortPosesSkipTheLastFrame) {
  const fs::path seq = dir_ / "seq";
  fs::copy(kData + "/kitti_odometry_excerpt/seq_a", seq, fs::copy_options::recursive);
  std::string poses = Slurp(seq / "poses.txt");
  poses = poses.substr(0, poses.rfind('\n') + 1);  // drop the last (unterminated) line
  Write(seq / "poses.txt", poses);
  absl::StatusOr<DriveLog> log = OpenLog(seq.string());
  ASSERT_TRUE(log.ok()) << log.status();
  EXPECT_EQ(log->frames.size(), 50u);
  EXPECT_TRUE(Mentions(*log, "50 poses for 51 images"));
  EXPECT_TRUE(Mentions(*log, "without a pose skipped: 50"));
}

TEST_F(Malformed, OdometryCalibLineWithElevenValues) {
  const fs::path seq = dir_ / "seq";
  fs::copy(kData + "/kitti_odometry_excerpt/seq_a", seq, fs::copy_options::recursive);
  Edit(seq / "calib.txt", "0.000000000000e+00 ", "");
  EXPECT_TRUE(ErrorSays(OpenLog(seq.string()).status(), "calib.txt: line 1: expected 12 values, got 11"));
}

class MalformedColmap : public Malformed {
 protected:
  fs::path CopyModel() {
    const fs::path model = dir_ / "sparse";
    fs::copy(kData + "/colmap_plush/sparse_txt_images_4", model, fs::copy_options::recursive);
    return model;
  }
};

TEST_F(MalformedColmap, ImageOfAnUnknownCamera) {
  const fs::path model = CopyModel();
  Edit(model / "images.txt", " 1 20240212_003921.jpg", " 2 20240212_003921.jpg");
  EXPECT_TRUE(ErrorSays(ReadColmapText(model.string()).status(), "images.txt: image 3", "camera 2"));
}

TEST_F(MalformedColmap, WrongParameterCount) {
  const fs::path model = CopyModel();
  Edit(model / "cameras.txt", " 0.03212323858", "");
  EXPECT_TRUE(ErrorSays(ReadColmapText(model.string()).status(), "cameras.txt: line 2", "SIMPLE_RADIAL takes 4 parameters, got 3"));
}

TEST_F(MalformedColmap, UnsupportedModel) {
  const fs::path model = CopyModel();
  Edit(model / "cameras.txt", "SIMPLE_RADIAL", "FOV");
  EXPECT_TRUE(ErrorSays(ReadColmapText(model.string()).status(), "cameras.txt: line 2", "'FOV' not supported"));
}

TEST_F(MalformedColmap, NonUnitQuaternion) {
  const fs::path model = CopyModel();
  Edit(model / "images.txt", "1 0.993793113238", "1 1.993793113238");
  EXPECT_TRUE(ErrorSays(ReadColmapText(model.string()).status(), "images.txt: line 2", "quaternion norm"));
}

TEST_F(MalformedColmap, NanPoint) {
  const fs::path model = CopyModel();
  Edit(model / "points3D.txt", "-1.38188248", "nan");
  EXPECT_TRUE(ErrorSays(ReadColmapText(model.string()).status(), "points3D.txt: line 2", "non-finite"));
}

TEST_F(MalformedColmap, TruncatedBinaryFiles) {
  absl::StatusOr<ColmapModel> text = ReadColmapText(CopyModel().string());
  ASSERT_TRUE(text.ok());
  const fs::path bin = dir_ / "bin";
  fs::create_directories(bin);
  ASSERT_TRUE(WriteColmapBinary(*text, bin.string()).ok());
  ASSERT_TRUE(ReadColmapBinary(bin.string()).ok());
  fs::resize_file(bin / "images.bin", fs::file_size(bin / "images.bin") - 5);
  EXPECT_TRUE(ErrorSays(ReadColmapBinary(bin.string()).status(), "images.bin: truncated at byte"));
  ASSERT_TRUE(WriteColmapBinary(*text, bin.string()).ok());
  fs::resize_file(bin / "points3D.bin", 20);
  EXPECT_TRUE(ErrorSays(ReadColmapBinary(bin.string()).status(), "points3D.bin", "does not fit the file"));
}

}  // namespace
}  // namespace streetsim
