#include "server/job_store.h"

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>

#include <google/protobuf/util/json_util.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "render/common/log.h"
#include "server/replica.h"

namespace streetsim::server {
namespace fs = std::filesystem;

int64_t NowUnixMs() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(
             std::chrono::system_clock::now().time_since_epoch()).count();
}

namespace {

absl::Status WriteFileAtomic(const std::string& path, const std::string& content) {
  const std::string tmp = path + ".tmp";
  const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) return absl::InternalError(absl::StrCat("cannot write ", tmp));
  size_t done = 0;
  while (done < content.size()) {
    const ssize_t n = ::write(fd, content.data() + done, content.size() - done);
    if (n <= 0) {
      ::close(fd);
      return absl::InternalError(absl::StrCat("write failed: ", tmp));
    }
    done += n;
  }
  ::fsync(fd);
  ::close(fd);
  if (std::rename(tmp.c_str(), path.c_str()) != 0) {
    return absl::InternalError(absl::StrCat("rename failed: ", path));
  }
  return absl::OkStatus();
}

}  // namespace

JobStore::JobStore(std::string state_dir, std::string replica)
    : state_dir_(std::move(state_dir)),
      replica_(std::move(replica)),
      jobs_dir_(state_dir_ + "/jobs"),
      scenes_dir_(state_dir_ + "/scenes") {}

bool JobStore::Owns(const std::string& id) const { return ReplicaOfId(id) == replica_; }

std::optional<v1::Job> JobStore::ReadRecord(const std::string& id) const {
  // The id names a directory: only what this store's NewId could have made (no '/', no "..").
  if (id.empty() || id.size() > 128 || id.front() == '.' ||
      id.find_first_not_of("abcdefghijklmnopqrstuvwxyz0123456789-.") != std::string::npos ||
      id.find("..") != std::string::npos) {
    return std::nullopt;
  }
  const std::string path = JobDir(id) + "/job.json";
  std::ifstream in(path);
  if (!in) return std::nullopt;
  std::stringstream ss;
  ss << in.rdbuf();
  v1::Job job;
  google::protobuf::util::JsonParseOptions opts;
  opts.ignore_unknown_fields = true;
  if (!google::protobuf::util::JsonStringToMessage(ss.str(), &job, opts).ok() || job.job_id() != id) {
    LOG(WARNING) << "skipping unreadable job record " << path;
    return std::nullopt;
  }
  return job;
}

std::vector<v1::Job> JobStore::ReadForeignRecords() const {
  std::vector<v1::Job> out;
  std::error_code ec;
  for (const fs::directory_entry& d : fs::directory_iterator(jobs_dir_, ec)) {
    const std::string id = d.path().filename().string();
    if (Owns(id)) continue;
    if (std::optional<v1::Job> job = ReadRecord(id)) out.push_back(*std::move(job));
  }
  return out;
}

absl::Status JobStore::Init() {
  std::error_code ec;
  fs::create_directories(jobs_dir_, ec);
  if (ec) return absl::InvalidArgumentError(absl::StrCat("cannot create ", jobs_dir_, ": ", ec.message()));
  fs::create_directories(scenes_dir_, ec);
  if (ec) return absl::InvalidArgumentError(absl::StrCat("cannot create ", scenes_dir_, ": ", ec.message()));
  std::lock_guard<std::mutex> lock(mu_);
  for (const fs::directory_entry& d : fs::directory_iterator(jobs_dir_, ec)) {
    const std::string id = d.path().filename().string();
    if (!Owns(id)) continue;
    if (std::optional<v1::Job> job = ReadRecord(id)) jobs_[id] = *std::move(job);
  }
  return absl::OkStatus();
}

std::vector<v1::Job> JobStore::List() {
  std::vector<v1::Job> out = ReadForeignRecords();
  std::lock_guard<std::mutex> lock(mu_);
  for (const auto& [id, job] : jobs_) out.push_back(job);
  std::sort(out.begin(), out.end(), [](const v1::Job& a, const v1::Job& b) {
    return a.created_unix_ms() != b.created_unix_ms() ? a.created_unix_ms() < b.created_unix_ms()
                                                      : a.job_id() < b.job_id();
  });
  return out;
}

std::optional<v1::Job> JobStore::Get(const std::string& id) {
  if (!Owns(id)) return ReadRecord(id);
  std::lock_guard<std::mutex> lock(mu_);
  auto it = jobs_.find(id);
  if (it == jobs_.end()) return std::nullopt;
  return it->second;
}

std::optional<v1::Job> JobStore::FindByRequestId(const std::string& request_id) {
  {
    std::lock_guard<std::mutex> lock(mu_);
    for (const auto& [id, job] : jobs_) {
      if (job.request_id() == request_id) return job;
    }
  }
  // A retry that reached another replica than the first attempt finds the job there.
  for (v1::Job& job : ReadForeignRecords()) {
    if (job.request_id() == request_id) return std::move(job);
  }
  return std::nullopt;
}

absl::Status JobStore::Put(v1::Job job) {
  if (!Owns(job.job_id())) {
    return absl::FailedPreconditionError(absl::StrCat("job ", job.job_id(), " belongs to another replica"));
  }
  job.set_updated_unix_ms(NowUnixMs());
  std::string json;
  google::protobuf::util::JsonPrintOptions opts;
  opts.preserve_proto_field_names = true;
  opts.add_whitespace = true;
  if (!google::protobuf::util::MessageToJsonString(job, &json, opts).ok()) {
    return absl::InternalError("cannot serialise job record");
  }
  const std::string dir = JobDir(job.job_id());
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (absl::Status s = WriteFileAtomic(dir + "/job.json", json); !s.ok()) return s;
  std::lock_guard<std::mutex> lock(mu_);
  jobs_[job.job_id()] = std::move(job);
  ++version_;
  cv_.notify_all();
  return absl::OkStatus();
}

std::string JobStore::NewId() {
  std::lock_guard<std::mutex> lock(mu_);
  while (true) {
    std::string id = ReplicaScopedId(replica_, absl::StrFormat("j-%d-%d", NowUnixMs(), ++counter_));
    if (!jobs_.count(id) && !fs::exists(JobDir(id))) return id;
  }
}

int JobStore::size() {
  std::lock_guard<std::mutex> lock(mu_);
  return static_cast<int>(jobs_.size());
}

uint64_t JobStore::version() {
  std::lock_guard<std::mutex> lock(mu_);
  return version_;
}

uint64_t JobStore::WaitForChange(uint64_t seen, std::chrono::milliseconds timeout) {
  std::unique_lock<std::mutex> lock(mu_);
  cv_.wait_for(lock, timeout, [&] { return version_ != seen; });
  return version_;
}

}  // namespace streetsim::server
