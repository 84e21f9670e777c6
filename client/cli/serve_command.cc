// streetsim serve: run the gRPC server (docs/server.md) until SIGTERM / SIGINT.
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <filesystem>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "client/cli/args.h"
#include "client/cli/commands.h"
#include "client/cli/static_skip_flags.h"
#include "scene/train/dynamic_stage.h"
#include "server/server_main.h"

namespace streetsim {
namespace {

int FailServe(int code, const absl::Status& status) { return ReportFailure("serve", code, status); }

// `streetsim serve` is streetsim, so a job's init and train stages run this very program, whatever
// its file is called (an install may version it; a `streetsim` beside it may be another build).
// "" when the file is gone (replaced since the start reads "... (deleted)"): the job runner then
// falls back to the `streetsim` next to it.
std::string ThisProgram() {
  std::error_code ec;
  const std::filesystem::path exe = std::filesystem::read_symlink("/proc/self/exe", ec);
  if (ec || !std::filesystem::is_regular_file(exe, ec)) return "";
  return exe.string();
}

template <typename T>
absl::Status ParseInt(const ParsedArgs& args, const std::string& flag, T min, T* out) {
  if (auto v = args.Get(flag)) {
    T n;
    if (!absl::SimpleAtoi(*v, &n) || n < min) {
      return absl::InvalidArgumentError(absl::StrCat("--", flag, " '", *v, "': expected an integer >= ", min));
    }
    *out = n;
  }
  return absl::OkStatus();
}

}  // namespace

int RunServeCommand(const std::vector<std::string>& argv) {
  std::vector<FlagSpec> flags = {{"listen"},       {"data-root"},        {"state-dir"},      {"backend"},
                                 {"tls-cert"},     {"tls-key"},          {"auth-token-file"}, {"max-sessions"},
                                 {"max-queued-renders"}, {"max-image-side"}, {"session-lease-s"},
                                 {"max-message-mb"}, {"init-command"},   {"field-device"},
                                 {"max-request-pixels"}, {"max-queued-renders-per-client"}, {"replica"}};
  flags.insert(flags.end(), StaticSkipFlags().begin(), StaticSkipFlags().end());
  absl::StatusOr<ParsedArgs> args = ParsedArgs::Parse(argv, flags);
  if (!args.ok()) return FailServe(2, args.status());
  if (!args->positional().empty()) {
    return FailServe(2, absl::InvalidArgumentError(absl::StrCat("unexpected argument '", args->positional()[0], "'")));
  }
  server::ServerOptions o;
  o.listen = args->Get("listen").value_or(o.listen);
  if (o.listen.rfind(':') == std::string::npos) return FailServe(2, absl::InvalidArgumentError("--listen takes HOST:PORT"));
  o.data_root = args->Get("data-root").value_or(o.data_root);
  o.state_dir = args->Get("state-dir").value_or(o.state_dir);
  absl::StatusOr<Backend> backend = ParseBackend(args->Get("backend").value_or("auto"));
  if (!backend.ok()) return FailServe(2, backend.status());
  o.backend = *backend;
  absl::StatusOr<train::FieldDevice> field_device =
      train::ParseFieldDevice(args->Get("field-device").value_or("auto"));
  if (!field_device.ok()) return FailServe(2, field_device.status());
  o.field_device = *field_device;
  absl::StatusOr<field::StaticSkipOptions> skip = StaticSkipFromFlags(*args);
  if (!skip.ok()) return FailServe(2, skip.status());
  o.static_skip = *skip;
  absl::StatusOr<bool> exact_field = ExactFieldFromFlags(*args);
  if (!exact_field.ok()) return FailServe(2, exact_field.status());
  o.exact_field = *exact_field;
  o.tls_cert_file = args->Get("tls-cert").value_or("");
  o.tls_key_file = args->Get("tls-key").value_or("");
  o.auth_token_file = args->Get("auth-token-file").value_or("");
  // A StatefulSet pod passes its own name through the environment (docs/deploy.md).
  const char* replica_env = std::getenv("STREETSIM_REPLICA");
  o.replica = args->Get("replica").value_or(replica_env ? replica_env : "");
  int side = 0;
  int64_t lease_s = 0, message_mb = 0;
  for (const absl::Status& s : {ParseInt(*args, "max-sessions", 1, &o.limits.max_sessions),
                                ParseInt(*args, "max-queued-renders", 0, &o.limits.max_queued_renders),
                                ParseInt(*args, "max-queued-renders-per-client", 1,
                                         &o.limits.max_queued_renders_per_client),
                                ParseInt<int64_t>(*args, "max-request-pixels", 1, &o.limits.max_request_pixels),
                                ParseInt(*args, "max-image-side", 1, &side),
                                ParseInt<int64_t>(*args, "session-lease-s", 1, &lease_s),
                                ParseInt<int64_t>(*args, "max-message-mb", 1, &message_mb)}) {
    if (!s.ok()) return FailServe(2, s);
  }
  if (side > 0) o.limits.max_image_width = o.limits.max_image_height = std::min(side, kMaxImageSide);
  if (lease_s > 0) o.limits.session_lease_ms = lease_s * 1000;
  if (message_mb > 0) o.limits.max_message_bytes = std::min<int64_t>(message_mb, 2000) << 20;
  if (const std::string self = ThisProgram(); !self.empty()) {
    o.init_command = {self, "init"};
    o.train_command = {self, "train"};
  }
  if (auto cmd = args->Get("init-command")) o.init_command = absl::StrSplit(*cmd, ' ', absl::SkipEmpty());
  return server::RunServerUntilSignal(o);
}

}  // namespace streetsim
