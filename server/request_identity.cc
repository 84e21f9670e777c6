#include "server/request_identity.h"

#include <google/protobuf/io/coded_stream.h>
#include <google/protobuf/io/zero_copy_stream_impl_lite.h>

#include "absl/strings/str_cat.h"
#include "server/echo.h"

namespace streetsim::server {

std::string Fingerprint(const google::protobuf::Message& message) {
  std::string out;
  {
    google::protobuf::io::StringOutputStream stream(&out);
    google::protobuf::io::CodedOutputStream coded(&stream);
    coded.SetSerializationDeterministic(true);
    message.SerializeToCodedStream(&coded);
  }
  return out;
}

absl::Status RequestIdReused(const std::string& request_id, const std::string& what) {
  return absl::InvalidArgumentError(absl::StrCat("request_id ", Echo(request_id), " was already used for a different ",
                                                 what, ": a new request needs a new request_id"));
}

}  // namespace streetsim::server
