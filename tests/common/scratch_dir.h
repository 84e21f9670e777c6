// Per-process scratch directories for tests: named `<prefix>_<name>_<pid>` under gtest's TempDir
// (tests of one binary run in parallel under ctest -j, and two checkouts may run the suite at
// once), emptied when created and removed when the test binary's tests end, pass or fail.
#pragma once

#include <unistd.h>

#include <filesystem>
#include <string>
#include <system_error>
#include <vector>

#include <gtest/gtest.h>

namespace streetsim::testing {

namespace scratch_internal {
inline std::vector<std::string>& Dirs() {
  static std::vector<std::string> dirs;
  return dirs;
}
struct RemoveAtExit : ::testing::Environment {
  void TearDown() override {
    std::error_code ec;
    for (const std::string& d : Dirs()) std::filesystem::remove_all(d, ec);
  }
};
inline void RegisterOnce() {
  [[maybe_unused]] static ::testing::Environment* const env = ::testing::AddGlobalTestEnvironment(new RemoveAtExit);
}
}  // namespace scratch_internal

// An empty directory (created) for this process; removed at the end of the run.
inline std::string ScratchDir(const std::string& prefix, const std::string& name) {
  const std::filesystem::path p =
      std::filesystem::path(::testing::TempDir()) / (prefix + "_" + name + "_" + std::to_string(getpid()));
  std::error_code ec;
  std::filesystem::remove_all(p, ec);
  std::filesystem::create_directories(p, ec);
  scratch_internal::RegisterOnce();
  scratch_internal::Dirs().push_back(p.string());
  return p.string();
}

}  // namespace streetsim::testing
