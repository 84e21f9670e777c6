// The server-side CLI through the built binary (${STREETSIM_BINARY_DIR}/bin/streetsim): `serve`
// as a child process (ephemeral port read from its "listening on" line, SIGTERM -> exit 0),
// `scenes`, `render --server` (pixel-equal to a local `render --ply`), `replay`, `jobs` with the
// fake init stage, TLS and token flags, and bad flags (exit 2, one line on stderr).
#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "server/child_process.h"
#include "tests/common/cli_runner.h"
#include "tests/server/server_fixture.h"

namespace streetsim::testing {
namespace {

const std::string kBinary = std::string(STREETSIM_BINARY_DIR) + "/bin/streetsim";
const std::string kFakeInit = std::string(STREETSIM_SOURCE_DIR) + "/tests/server/fake_init.sh";

struct Result {
  int exit_code;
  std::string out, err;
};

std::string ReadAll(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  return std::string((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
}

int Lines(const std::string& s) { return static_cast<int>(std::count(s.begin(), s.end(), '\n')); }

bool Contains(const std::string& haystack, const std::string& needle) {
  return haystack.find(needle) != std::string::npos;
}

// `streetsim serve ...` as a child: stdout through a pipe (for the "listening on" line), stderr
// to a file.
class ServeProcess {
 public:
  ~ServeProcess() {
    if (pid_ > 0) {
      kill(pid_, SIGKILL);
      waitpid(pid_, nullptr, 0);
    }
    if (out_fd_ >= 0) close(out_fd_);
  }
  // Starts it and waits for "streetsim serve: listening on HOST:PORT"; false if it did not come.
  bool Start(const std::vector<std::string>& flags, const std::string& stderr_path,
             const std::string& binary = kBinary) {
    stderr_path_ = stderr_path;
    std::vector<std::string> argv = {binary, "serve"};
    argv.insert(argv.end(), flags.begin(), flags.end());
    absl::StatusOr<server::PipedChild> child = server::SpawnWithPipedStdout(argv, stderr_path);
    if (!child.ok()) return false;
    pid_ = child->pid;
    out_fd_ = child->stdout_fd;
    std::string out;
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(30);
    while (!Contains(out, "\n")) {
      const auto left =
          std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now()).count();
      pollfd pfd{out_fd_, POLLIN, 0};
      if (left <= 0 || poll(&pfd, 1, static_cast<int>(left)) <= 0) return false;
      char buf[256];
      const ssize_t n = read(out_fd_, buf, sizeof(buf));
      if (n <= 0) return false;
      out.append(buf, n);
    }
    const std::string prefix = "streetsim serve: listening on ";
    if (out.rfind(prefix, 0) != 0) return false;
    address_ = out.substr(prefix.size(), out.find('\n') - prefix.size());
    return true;
  }
  // SIGTERM, then the exit code (-1 if it did not exit within 20 s or died of a signal).
  int Terminate() {
    if (pid_ <= 0) return -1;
    kill(pid_, SIGTERM);
    int status = 0;
    for (int i = 0; i < 2000; ++i) {
      if (waitpid(pid_, &status, WNOHANG) == pid_) {
        pid_ = -1;
        return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    return -1;
  }
  const std::string& address() const { return address_; }
  std::string stderr_text() const { return ReadAll(stderr_path_); }

 private:
  pid_t pid_ = -1;
  int out_fd_ = -1;
  std::string address_, stderr_path_;
};

class CliServerTest : public ::testing::Test {
 protected:
  void SetUp() override {
    data_root_ = MakeDataRoot();
    state_dir_ = MakeTempDir("state");
    dir_ = MakeTempDir("cli");
  }
  void TearDown() override {
    serve_.reset();
    std::error_code ec;
    for (const std::string& d : {data_root_, state_dir_, dir_}) fs::remove_all(d, ec);
  }
  std::vector<std::string> ServeFlags() {
    return {"--listen", "127.0.0.1:0", "--data-root", data_root_, "--state-dir", state_dir_, "--backend", "cpu",
            "--init-command", "/bin/sh " + kFakeInit};
  }
  void StartServe(std::vector<std::string> extra = {}, const std::string& binary = kBinary) {
    std::vector<std::string> flags = ServeFlags();
    flags.insert(flags.end(), extra.begin(), extra.end());
    serve_ = std::make_unique<ServeProcess>();
    ASSERT_TRUE(serve_->Start(flags, dir_ + "/serve.stderr", binary)) << serve_->stderr_text();
  }
  Result Exec(const std::string& args) {
    const std::string out = dir_ + "/cmd.stdout", err = dir_ + "/cmd.stderr";
    const int status = std::system((kBinary + " " + cli_test::WithoutActorsUnlessNamed(args) + " >" + out + " 2>" + err).c_str());
    return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, ReadAll(out), ReadAll(err)};
  }
  std::string Server() { return " --server " + serve_->address(); }
  void ExpectRefused(const std::string& args, int code, const std::string& needle) {
    const Result r = Exec(args);
    EXPECT_EQ(r.exit_code, code) << args << "\n" << r.err;
    EXPECT_EQ(Lines(r.err), 1) << args << "\n" << r.err;
    EXPECT_TRUE(Contains(r.err, needle)) << args << ": wanted '" << needle << "' in: " << r.err;
  }

  std::string data_root_, state_dir_, dir_;
  std::unique_ptr<ServeProcess> serve_;
};

TEST_F(CliServerTest, ServeListsScenesAndExitsZeroOnSigterm) {
  StartServe();
  EXPECT_TRUE(Contains(serve_->address(), "127.0.0.1:"));
  EXPECT_NE(serve_->address(), "127.0.0.1:0");
  Result r = Exec("scenes" + Server());
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_TRUE(Contains(r.out, "api 1.0.0")) << r.out;
  EXPECT_TRUE(Contains(r.out, "street ")) << r.out;
  EXPECT_TRUE(Contains(r.out, "timed ")) << r.out;
  EXPECT_TRUE(Contains(r.out, "0..2000000")) << r.out;
  EXPECT_TRUE(Contains(r.out, "cam_front(128x64),cam_left(96x64)")) << r.out;
  r = Exec("scenes" + Server() + " --load timed");
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_TRUE(Contains(r.out, "timed: ready, 4000 Gaussians")) << r.out;
  r = Exec("scenes" + Server() + " --info timed");
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_TRUE(Contains(r.out, "cam_left")) << r.out;
  r = Exec("scenes" + Server());
  EXPECT_TRUE(Contains(r.out, "1 scenes loaded")) << r.out;
  EXPECT_EQ(Exec("scenes" + Server() + " --unload timed").exit_code, 0);
  ExpectRefused("scenes" + Server() + " --load nope", 2, "nope");
  ExpectRefused("scenes" + Server() + " --info ../etc", 2, "streetsim scenes:");
  EXPECT_EQ(serve_->Terminate(), 0) << serve_->stderr_text();
  EXPECT_TRUE(Contains(serve_->stderr_text(), "SIGTERM, draining")) << serve_->stderr_text();
  // Gone: a failure on the way, exit 1.
  ExpectRefused("scenes" + Server() + " --timeout-s 2", 1, "streetsim scenes:");
}

TEST_F(CliServerTest, RemoteRenderMatchesLocalRender) {
  StartServe();
  const std::string cam = dir_ + "/cam.json", local = dir_ + "/local.png", remote = dir_ + "/remote.png",
                    remote_ply = dir_ + "/remote_ply.png";
  Result r = Exec("ply-info " + data_root_ + "/street.ply --camera-out " + cam + " --width 320 --height 96");
  ASSERT_EQ(r.exit_code, 0) << r.err;
  r = Exec("render --backend cpu --ply " + data_root_ + "/street.ply --camera " + cam + " --out-rgb " + local);
  ASSERT_EQ(r.exit_code, 0) << r.err;
  r = Exec("render" + Server() + " --scene street --camera " + cam + " --out-rgb " + remote);
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_EQ(Lines(r.err), 1) << r.err;
  EXPECT_TRUE(Contains(r.err, "on the server")) << r.err;
  r = Exec("render" + Server() + " --ply street.ply --camera " + cam + " --out-rgb " + remote_ply);
  ASSERT_EQ(r.exit_code, 0) << r.err;
  const cv::Mat a = cv::imread(local, cv::IMREAD_UNCHANGED), b = cv::imread(remote, cv::IMREAD_UNCHANGED),
                c = cv::imread(remote_ply, cv::IMREAD_UNCHANGED);
  ASSERT_EQ(a.type(), CV_8UC3);
  ASSERT_EQ(b.type(), CV_8UC3);
  ASSERT_EQ(a.size(), cv::Size(320, 96));
  ASSERT_EQ(b.size(), a.size());
  EXPECT_EQ(cv::norm(a, b, cv::NORM_INF), 0) << "remote and local renders differ";
  EXPECT_EQ(cv::norm(b, c, cv::NORM_INF), 0);
  EXPECT_GT(cv::countNonZero(a.reshape(1)), 320 * 96 / 10);  // not an empty frame
  if (ReadAll(local) != ReadAll(remote)) std::printf("(PNG bytes differ, pixels equal: different PNG encoders)\n");
  // Server-side refusals keep the CLI contract.
  ExpectRefused("render" + Server() + " --scene nope --camera " + cam + " --out-rgb " + dir_ + "/x.png", 2, "nope");
  ExpectRefused("render" + Server() + " --camera " + cam + " --out-rgb " + dir_ + "/x.png", 2, "--scene");
  ExpectRefused("render" + Server() + " --scene street --ply street.ply --camera " + cam + " --out-rgb " + dir_ +
                    "/x.png", 2, "not both");
  ExpectRefused("render" + Server() + " --scene timed --time-us 9000000 --camera " + cam + " --out-rgb " + dir_ +
                    "/x.png", 2, "streetsim render:");
  EXPECT_FALSE(fs::exists(dir_ + "/x.png"));
}

TEST_F(CliServerTest, ReplayWritesFramesVideosAndSummary) {
  StartServe();
  const std::string scenario = dir_ + "/scenario.json", out = dir_ + "/replay";
  std::ofstream(scenario) << R"({"scene": "timed", "num_steps": 4, "step_dt_us": 100000, "width": 64, "height": 32,
    "ego": {"mode": "log", "lateral_offset_m": 0.5}})";
  Result r = Exec("replay " + scenario + " --out " + out + Server());
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_TRUE(Contains(r.err, "4 steps of timed")) << r.err;
  for (int k = 0; k < 4; ++k) {
    for (const char* sensor : {"cam_front", "cam_left"}) {
      const std::string frame = out + "/frames/step_0000" + std::to_string(k) + "_" + sensor + ".png";
      const cv::Mat img = cv::imread(frame, cv::IMREAD_UNCHANGED);
      ASSERT_FALSE(img.empty()) << frame;
      EXPECT_EQ(img.size(), cv::Size(64, 32));
    }
  }
  for (const char* video : {"/cam_front.avi", "/cam_left.avi"}) {
    std::error_code ec;
    EXPECT_GT(fs::file_size(out + video, ec), 1000u) << video;
  }
  const nlohmann::json summary = nlohmann::json::parse(ReadAll(out + "/summary.json"), nullptr, false);
  ASSERT_FALSE(summary.is_discarded());
  EXPECT_EQ(summary["scene"], "timed");
  EXPECT_EQ(summary["num_steps"], 4);
  ASSERT_EQ(summary["steps"].size(), 4u);
  EXPECT_EQ(summary["steps"][3]["time_us"], 300000);
  // The log trajectory moves 10 m/s along x; the offset is 0.5 m to the left (+y).
  EXPECT_NEAR(summary["steps"][3]["ego_xyz_m"][0].get<double>(), 3.0, 1e-6);
  EXPECT_NEAR(summary["steps"][3]["ego_xyz_m"][1].get<double>(), 0.5, 1e-6);
  EXPECT_TRUE(Contains(summary["steps"][0]["content_digest"].get<std::string>(), "fnv1a64w:"));
  EXPECT_EQ(summary["videos"].size(), 2u);
  // Bad scenarios: exit 2, one line.
  std::ofstream(dir_ + "/bad.json") << R"({"scene": "timed"})";
  ExpectRefused("replay " + dir_ + "/bad.json --out " + out + Server(), 2, "num_steps");
  std::ofstream(dir_ + "/nope.json") << R"({"scene": "nope", "num_steps": 2})";
  ExpectRefused("replay " + dir_ + "/nope.json --out " + out + Server(), 2, "nope");
  std::ofstream(dir_ + "/static.json") << R"({"scene": "street", "num_steps": 2})";
  ExpectRefused("replay " + dir_ + "/static.json --out " + out + Server(), 2, "ego trajectory");
  ExpectRefused("replay " + dir_ + "/missing.json" + Server(), 2, "cannot open");
  // A value of the wrong type or range names its field (it once ended the process on an exception).
  const std::vector<std::pair<std::string, std::string>> ill_typed = {
      {R"({"scene": "timed", "num_steps": 2, "server": 5})", "\"server\" must be a string"},
      {R"({"scene": "timed", "num_steps": "three"})", "\"num_steps\" must be an integer"},
      {R"({"scene": "timed", "num_steps": 1e12})", "\"num_steps\" must be an integer"},
      {R"({"scene": ["timed"], "num_steps": 2})", "\"scene\" must be a string"},
      {R"({"scene": "timed", "num_steps": 2, "sensors": [0]})", "\"sensors\" must be a list of strings"},
      {R"({"scene": "timed", "num_steps": 2, "step_dt_us": 0})", "step_dt_us"},
      {R"({"scene": "timed", "num_steps": 2, "seed": -1})", "\"seed\" must be a non-negative integer"},
      {R"({"scene": "timed", "num_steps": 2, "video_fps": 0})", "video_fps"},
      {R"({"scene": "timed", "num_steps": 2, "ego": {"mode": "log", "lateral_offset_m": "left"}})",
       "ego.\"lateral_offset_m\" must be a number"},
      {R"({"scene": "timed", "num_steps": 2, "ego": {"mode": 3}})", "ego.\"mode\" must be a string"},
      {R"({"scene": "timed", "num_steps": 2, "ego": {"mode": "straight", "start": [1, 2]}})", "ego.start"},
      {R"({"scene": "timed", "num_steps": 2, "actors": [{"actor_id": 1, "edit": 7}]})", "\"edit\" must be a string"},
      {R"([1, 2])", "not a JSON object"}};
  for (const auto& [text, needle] : ill_typed) {
    std::ofstream(dir_ + "/typed.json", std::ios::trunc) << text;
    ExpectRefused("replay " + dir_ + "/typed.json --out " + out + Server(), 2, needle);
  }
  ExpectRefused("replay" + Server(), 2, "usage: streetsim replay");
}

TEST_F(CliServerTest, JobsTrainWatchListGet) {
  StartServe();
  Result r = Exec("jobs list" + Server());
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_EQ(r.out, "");
  r = Exec("jobs train logs/fake --scene-name cli_job --request-id rq1 --max-iterations 0 --watch" + Server());
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_TRUE(Contains(r.out, "succeeded")) << r.out;
  EXPECT_TRUE(Contains(r.out, "scene cli_job")) << r.out;
  const std::string id = r.out.substr(0, r.out.find(' '));
  ASSERT_EQ(id.rfind("j-", 0), 0u) << r.out;
  r = Exec("jobs" + Server());  // list is the default
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_TRUE(Contains(r.out, id + "  succeeded")) << r.out;
  r = Exec("jobs get " + id + Server());
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_TRUE(Contains(r.out, "done")) << r.out;
  r = Exec("jobs watch " + id + Server());
  EXPECT_EQ(r.exit_code, 0) << r.err;
  // Idempotent by request id; the scene name is now taken.
  r = Exec("jobs train logs/fake --scene-name cli_job --request-id rq1 --max-iterations 0" + Server());
  EXPECT_EQ(r.exit_code, 0) << r.err;
  EXPECT_TRUE(Contains(r.out, id)) << r.out;
  ExpectRefused("jobs train logs/fake --scene-name cli_job --max-iterations 0" + Server(), 2, "already");
  r = Exec("scenes" + Server());
  EXPECT_TRUE(Contains(r.out, "cli_job")) << r.out;
  ExpectRefused("jobs get j-nope" + Server(), 2, "j-nope");
  ExpectRefused("jobs train ../outside" + Server(), 2, "log_path");
  ExpectRefused("jobs train logs/missing" + Server(), 2, "log_path");
  ExpectRefused("jobs train logs/fake --max-iterations -3" + Server(), 2, "--max-iterations");
  ExpectRefused("jobs frobnicate" + Server(), 2, "usage: streetsim jobs");
  ExpectRefused("jobs train" + Server(), 2, "usage: streetsim jobs");

  // With iterations, the server's `streetsim` runs its own `streetsim train` as the train
  // stage (when this build has it): on the fake log (no images) the trainer refuses it.
  const bool has_train = Contains(Exec("--help").out + Exec("--help").err, "\n  train ");
  r = Exec("jobs train logs/fake --scene-name with_iters --max-iterations 5 --watch" + Server());
  std::printf("(this build %s `streetsim train`)\n", has_train ? "has" : "has no");
  if (has_train) {
    EXPECT_EQ(r.exit_code, 1) << r.out << r.err;
    EXPECT_TRUE(Contains(r.out, "failed")) << r.out;
    EXPECT_TRUE(Contains(r.out, "train stage exited with code 2")) << r.out;
    EXPECT_TRUE(fs::exists(state_dir_ + "/jobs/" + r.out.substr(0, r.out.find(' ')) + "/train.log")) << r.out;
    // The trainer's own reason is in the job's error.
    EXPECT_TRUE(Contains(r.out, "not a recognised log")) << r.out;
  } else {
    EXPECT_EQ(r.exit_code, 0) << r.out << r.err;
  }
  EXPECT_EQ(serve_->Terminate(), 0) << serve_->stderr_text();
}

// An installed streetsim may carry another name (streetsim-1.4, a distribution's wrapper): its jobs
// run its own trainer, not a `streetsim` that is not beside it (the job failed "cannot start").
TEST_F(CliServerTest, JobsRunTheServingBinaryWhateverItsFileIsCalled) {
  const std::string renamed = dir_ + "/streetsim-renamed";
  std::error_code ec;
  ASSERT_TRUE(fs::copy_file(kBinary, renamed, ec)) << ec.message();
  StartServe({}, renamed);
  const Result r = Exec("jobs train logs/fake --scene-name renamed_job --max-iterations 5 --watch" + Server());
  EXPECT_EQ(r.exit_code, 1) << r.out << r.err;
  EXPECT_FALSE(Contains(r.out, "cannot start")) << r.out;
  // The trainer ran and refused the fake log.
  EXPECT_TRUE(Contains(r.out, "train stage exited with code 2")) << r.out;
  EXPECT_TRUE(Contains(r.out, "not a recognised log")) << r.out;
  EXPECT_EQ(serve_->Terminate(), 0) << serve_->stderr_text();
}

// Every training option of a job reaches the real `streetsim train` as a flag it accepts: with all
// of them set, the trainer gets past its flags and stops only at the fake log.
TEST_F(CliServerTest, JobsTrainPassesTheConfigToTheTrainer) {
  if (!Contains(Exec("--help").err + Exec("--help").out, "\n  train ")) GTEST_SKIP() << "no `streetsim train`";
  StartServe();
  const std::string options =
      " --max-iterations 12000 --seed 3 --field extended --field-modules temporal,decoder --static-iterations 4000"
      " --resolution-scale 0.5 --low-res-scale 0.25 --low-res-iterations 3000 --holdout-every 0"
      " --field-lr-scale 2.5 --field-lr-decay-iterations 6000 --backend cpu --pose-refinement"
      " --pose-lr-scale 3 --position-lr-decay-iterations 7000 --field-ext-lr-scale 0.4"
      " --field-ext-lr-decay-iterations 4500 --field-motion-prior 0.3 --field-motion-prior-scans all"
      " --densify-until 9000";
  Result r = Exec("jobs train logs/fake --scene-name all_options --watch" + options + Server());
  EXPECT_EQ(r.exit_code, 1) << r.out << r.err;
  EXPECT_TRUE(Contains(r.out, "train stage exited with code 2: ")) << r.out;
  EXPECT_TRUE(Contains(r.out, "not a recognised log")) << r.out;
  const std::string id = r.out.substr(0, r.out.find(' '));
  const std::string log = ReadAll(state_dir_ + "/jobs/" + id + "/train.log");
  EXPECT_EQ(Lines(log), 1) << log;  // the log's complaint only: no flag was refused
  // Values the trainer would refuse are refused by the server before a job exists.
  ExpectRefused("jobs train logs/fake --max-iterations 100 --field dynamic" + Server(), 2, "field must be one of");
  ExpectRefused("jobs train logs/fake --max-iterations 100 --low-res-scale 0.5 --low-res-iterations 200" + Server(), 2,
                "low-res-scale / low-res-iterations");
  ExpectRefused("jobs train logs/fake --max-iterations 100 --static-iterations many" + Server(), 2,
                "static-iterations must be an integer");
  ExpectRefused("jobs train logs/fake --max-iterations 9000 --field s3gaussian --field-ext-lr-scale 0.5" + Server(), 2,
                "needs field extended");
  ExpectRefused("jobs train logs/fake --max-iterations 9000 --field-motion-prior -1" + Server(), 2,
                "field-motion-prior must be a number in [0, 10000]");
  ExpectRefused("jobs train logs/fake --set field-motion-prior-scans=first" + Server(), 2,
                "config.settings['field-motion-prior-scans']");
  ExpectRefused("jobs train logs/fake --preset fastest" + Server(), 2, "no preset 'fastest'");
  r = Exec("jobs list" + Server());
  EXPECT_EQ(Lines(r.out), 1) << r.out;
  EXPECT_EQ(serve_->Terminate(), 0) << serve_->stderr_text();
}

TEST_F(CliServerTest, TlsAndTokenFlags) {
  const std::string cmd = "/usr/bin/openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -days 1"
                          " -subj /CN=localhost -addext subjectAltName=IP:127.0.0.1 -keyout " + dir_ +
                          "/key.pem -out " + dir_ + "/cert.pem >/dev/null 2>&1";
  ASSERT_EQ(std::system(cmd.c_str()), 0);
  std::ofstream(dir_ + "/token") << "cli-token\n";
  StartServe({"--tls-cert", dir_ + "/cert.pem", "--tls-key", dir_ + "/key.pem", "--auth-token-file", dir_ + "/token"});
  const std::string tls = " --tls-ca " + dir_ + "/cert.pem";
  Result r = Exec("scenes" + Server() + tls + " --token-file " + dir_ + "/token");
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_TRUE(Contains(r.out, "street")) << r.out;
  ExpectRefused("scenes" + Server() + tls, 2, "streetsim scenes:");  // no token: UNAUTHENTICATED
  ExpectRefused("scenes" + Server() + " --timeout-s 3 --token-file " + dir_ + "/token", 1, "streetsim scenes:");
  ExpectRefused("scenes" + Server() + " --tls-ca " + dir_ + "/missing.pem", 2, "missing.pem");
  ExpectRefused("scenes" + Server() + tls + " --token-file " + dir_ + "/missing", 2, "--token-file");
  EXPECT_EQ(serve_->Terminate(), 0) << serve_->stderr_text();
}

TEST_F(CliServerTest, BadServeFlagsExitTwoWithOneLine) {
  ExpectRefused("serve --frobnicate 1", 2, "--frobnicate");
  ExpectRefused("serve extra", 2, "unexpected argument");
  ExpectRefused("serve --listen nocolon", 2, "--listen");
  ExpectRefused("serve --max-sessions 0", 2, "--max-sessions");
  ExpectRefused("serve --max-queued-renders x", 2, "--max-queued-renders");
  ExpectRefused("serve --backend metal", 2, "metal");
  ExpectRefused("serve --listen 127.0.0.1:0 --data-root " + dir_ + "/nope", 2, "--data-root");
  ExpectRefused("serve --listen 127.0.0.1:0 --data-root " + data_root_ + " --state-dir " + state_dir_ +
                    " --tls-cert " + dir_ + "/c.pem",
                2, "--tls-cert and --tls-key");
  ExpectRefused("scenes --bogus", 2, "--bogus");
  ExpectRefused("scenes --server 127.0.0.1:1 --timeout-s -1", 2, "--timeout-s");
  ExpectRefused("render --server 127.0.0.1:1 --scene s --camera " + dir_ + "/none.json --out-rgb " + dir_ + "/o.png",
                2, "none.json");
}

}  // namespace
}  // namespace streetsim::testing
