#include "render/common/log.h"

#include <sys/time.h>

#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <mutex>

namespace streetsim::logging {
namespace {
int Threshold() {
  static const int threshold = [] {
    const char* env = std::getenv("STREETSIM_LOG_LEVEL");
    return env ? std::atoi(env) : 0;
  }();
  return threshold;
}
}  // namespace

bool Enabled(Severity severity) {
  return static_cast<int>(severity) >= Threshold() || severity == Severity::kFATAL;
}

LogMessage::LogMessage(Severity severity, const char* file, int line) : severity_(severity) {
  timeval tv;
  gettimeofday(&tv, nullptr);
  tm local;
  localtime_r(&tv.tv_sec, &local);
  const char* base = std::strrchr(file, '/');
  char prefix[64];
  std::snprintf(prefix, sizeof(prefix), "%c%02d%02d %02d:%02d:%02d.%03d ",
                "IWEF"[static_cast<int>(severity)], local.tm_mon + 1, local.tm_mday,
                local.tm_hour, local.tm_min, local.tm_sec, static_cast<int>(tv.tv_usec / 1000));
  stream_ << prefix << (base ? base + 1 : file) << ":" << line << "] ";
}

LogMessage::~LogMessage() {
  stream_ << '\n';
  static std::mutex mu;
  {
    std::lock_guard<std::mutex> lock(mu);
    const std::string s = stream_.str();
    std::fwrite(s.data(), 1, s.size(), stderr);
    std::fflush(stderr);
  }
  if (severity_ == Severity::kFATAL) std::abort();
}

}  // namespace streetsim::logging
