#include "server/echo.h"

#include "absl/strings/escaping.h"
#include "absl/strings/str_cat.h"

namespace streetsim::server {

std::string Echo(absl::string_view value) {
  if (value.size() <= kMaxEchoBytes) return absl::StrCat("'", absl::CHexEscape(value), "'");
  return absl::StrCat("'", absl::CHexEscape(value.substr(0, kMaxEchoBytes)), "...' (", value.size(), " bytes)");
}

}  // namespace streetsim::server
