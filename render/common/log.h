// Logging with absl's LOG(severity) << ... syntax.
//
// Debian bookworm's Abseil (20220623) predates absl/log, so streetsim carries this small stand-in
// with the same call syntax; moving to absl/log later is a header swap. Lines go to stderr as
// "I1122 11:45:00.123 file.cc:42] message". STREETSIM_LOG_LEVEL=0..3 (INFO..FATAL) sets the
// threshold (default 0 = INFO; 1 hides INFO).
#pragma once

#include <sstream>

namespace streetsim::logging {

enum class Severity { kINFO = 0, kWARNING = 1, kERROR = 2, kFATAL = 3 };

class LogMessage {
 public:
  LogMessage(Severity severity, const char* file, int line);
  ~LogMessage();  // writes the line; aborts for FATAL
  LogMessage(const LogMessage&) = delete;
  LogMessage& operator=(const LogMessage&) = delete;
  std::ostream& stream() { return stream_; }

 private:
  Severity severity_;
  std::ostringstream stream_;
};

bool Enabled(Severity severity);

}  // namespace streetsim::logging

#define STREETSIM_LOG(sev)                                                              \
  if (!::streetsim::logging::Enabled(::streetsim::logging::Severity::k##sev)) {         \
  } else                                                                                \
    ::streetsim::logging::LogMessage(::streetsim::logging::Severity::k##sev, __FILE__, \
                                     __LINE__)                                          \
        .stream()

#ifndef LOG
#define LOG(sev) STREETSIM_LOG(sev)
#endif
