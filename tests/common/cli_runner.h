// Running the built `streetsim` binary from a test: its path, the shared KITTI drive and front
// camera the CLI tests use, and one run with its exit code, stdout and stderr. Only for test
// targets (streetsim_add_test defines STREETSIM_BINARY_DIR, _DATA_DIR and _SOURCE_DIR).
#pragma once

#include <sys/wait.h>

#include <cstdlib>
#include <fstream>
#include <sstream>
#include <string>

namespace streetsim::cli_test {

inline const std::string kBinary = std::string(STREETSIM_BINARY_DIR) + "/bin/streetsim";
inline const std::string kKitti =
    std::string(STREETSIM_DATA_DIR) + "/kitti_raw/2011_09_26/2011_09_26_drive_sfnd_sync";
inline const std::string kKittiCamera = std::string(STREETSIM_SOURCE_DIR) + "/examples/cameras/kitti_front.json";

struct Result {
  int code;
  std::string out, err;
};

// The whole file ("" when it cannot be read).
inline std::string Slurp(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  std::stringstream s;
  s << f.rdbuf();
  return s.str();
}

// Tests that train on a LiDAR log to check something else leave out the run's last stage, actor
// extraction (about 10 s of LiDAR tracking on the KITTI clip, docs/actors.md); the tests of actors
// ask for it by naming the setting.
inline std::string WithoutActorsUnlessNamed(const std::string& args) {
  if (args.rfind("train ", 0) != 0 || args.find("actors") != std::string::npos) return args;
  return args + " --no-actors";
}

// Runs `streetsim ARGS` through the shell, stdout and stderr redirected to out_path and err_path
// (the caller's, so that tests running in parallel do not share them; left in place).
inline Result RunStreetsim(const std::string& args, const std::string& out_path, const std::string& err_path) {
  const int status =
      std::system((kBinary + " " + WithoutActorsUnlessNamed(args) + " >" + out_path + " 2>" + err_path).c_str());
  return Result{WEXITSTATUS(status), Slurp(out_path), Slurp(err_path)};
}

}  // namespace streetsim::cli_test
