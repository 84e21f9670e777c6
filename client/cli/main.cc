// The streetsim command-line tool.
#include <algorithm>
#include <cstdio>
#include <cstring>
#include <string>
#include <vector>

#include "client/cli/commands.h"
#include "client/cli/parent_server.h"

namespace {

constexpr char kUsage[] =
               "usage: streetsim <command> [flags]\n"
               "\n"
               "commands:\n"
               "  render    render a Gaussian scene from a camera:\n"
               "            streetsim render (--ply SCENE.ply | --scene DIR [--time-us T])\n"
               "              --camera CAMERA.json --out-rgb OUT.png\n"
               "              [--out-depth D.tiff] [--out-alpha A.tiff] [--background R,G,B]\n"
               "              [--backend auto|cpu|vulkan]\n"
               "            (--scene DIR: a trained scene, deformed by its field at T, clamped to\n"
               "            the log's time range; LiDAR: --lidar, docs/lidar.md; through a server:\n"
               "            --server HOST:PORT --scene NAME, docs/server.md)\n"
               "  ply-info  print a scene's size, SH degree and bounds; optionally write a camera\n"
               "            that frames it: streetsim ply-info SCENE.ply [--camera-out CAMERA.json]\n"
               "              [--width W] [--height H] [--view front|back|left|right|top]\n"
               "  devices   list the render backends and Vulkan devices of this machine\n"
               "  log       inspect a driving log (KITTI raw/odometry, COLMAP; docs/logs.md):\n"
               "            streetsim log info PATH\n"
               "            streetsim log preview PATH --frame N --out F.png [--camera NAME] [--max-depth M]\n"
               "            streetsim log poses PATH [--from-lidar] [--frames A:B] [--out POSES.txt]\n"
               "            streetsim log camera PATH --frame N --out CAMERA.json [--camera NAME]\n"
               "            streetsim log tracks PATH [--frames A:B] [--min-scans N] [--min-displacement-m M]\n"
               "              [--json OUT.json]   (moving objects followed in the LiDAR, no boxes)\n"
               "  init      initial Gaussians of a log: streetsim init PATH --out SCENE.ply [--frames A:B[:S]]\n"
               "              [--voxel M] [--max-range M] [--sky] [--drop-dynamic] [--random-points N]\n"
               "  serve     run the gRPC simulator server (docs/server.md): streetsim serve\n"
               "              [--listen HOST:PORT] [--data-root DIR] [--state-dir DIR] [--backend B]\n"
               "              [--field-device auto|cpu|vulkan] [--static-motion-m M] [--static-sh S]\n"
               "              [--field-serving served|exact] ...\n"
               "  scenes    list a server's scenes: streetsim scenes --server HOST:PORT\n"
               "  jobs      training jobs on a server: streetsim jobs list|train|watch|get|cancel ...\n"
               "              (jobs train LOG [--preset NAME] [--set NAME=VALUE]... takes train's settings)\n"
               "  replay    scripted replay through a server: streetsim replay SCENARIO.json\n"
               "  train     scene training (docs/training.md): streetsim train --log PATH --out DIR\n"
               "              [--preset quality|preview] [--config FILE.json] [--set NAME=VALUE]... [--resume]\n"
               "              (no other flag: the default preset, the measured best; every setting is a flag too;\n"
               "               streetsim train --help: the common settings, --help-all: every one)\n"
               "  eval      metrics of a trained scene: streetsim eval --scene DIR --log PATH [--split test|train] [--no-lidar]\n"
               "              [--decomposition DIR] [--video OUT.avi|OUT.mp4] [--video-fps F]\n"
               "              [--holdout-every K] [--served [--field-serving served|exact] [--static-motion-m M] [--static-sh S]] [--log-poses]\n"
               "              (a scene with DIR/pose_corrections.json is evaluated at its corrected poses;\n"
               "               --log-poses: at the log's)\n"
               "              (JSON on stdout, a table on stderr; --served: rendered as streetsim serve\n"
               "              serves it, the static skip's Gaussians baked, docs/field.md \"Serving\")\n"
               "  actors    a trained scene's actors (docs/actors.md): streetsim actors extract --scene DIR --log PATH\n"
               "              streetsim actors list --scene DIR [--json]   (train extracts them at its end)\n"
               "\n"
               "streetsim <command> --help: that command's part of this text.\n";

void PrintUsage(FILE* out) { std::fputs(kUsage, out); }

// `command`'s block of kUsage: its line and the indented lines that follow it.
std::string CommandUsage(const std::string& command) {
  const std::string text = kUsage, head = "  " + command + " ";
  std::string out;
  bool in = false;
  for (size_t b = 0; b < text.size();) {
    const size_t e = std::min(text.find('\n', b), text.size());
    const std::string line = text.substr(b, e - b);
    if (line.rfind(head, 0) == 0) {
      in = true;
    } else if (in && (line.size() < 3 || line[2] != ' ')) {
      break;
    }
    if (in) out += line + "\n";
    b = e + 1;
  }
  return out;
}

}  // namespace

int main(int argc, char** argv) {
  streetsim::DieWithParentServer();
  if (argc < 2 || !std::strcmp(argv[1], "--help") || !std::strcmp(argv[1], "-h") ||
      !std::strcmp(argv[1], "help")) {
    PrintUsage(argc < 2 ? stderr : stdout);
    return argc < 2 ? 2 : 0;
  }
  const std::string command = argv[1];
  const std::vector<std::string> args(argv + 2, argv + argc);
  for (const std::string& a : args) {
    if (a != "--help" && a != "-h") continue;
    if (command == "train") return streetsim::RunTrainCommand({"--help"});  // from the settings table
    const std::string usage = CommandUsage(command);
    if (usage.empty()) break;  // an unknown command: said below
    std::fputs(usage.c_str(), stdout);
    return 0;
  }
  if (command == "render") return streetsim::RunRenderCommand(args);
  if (command == "ply-info") return streetsim::RunPlyInfoCommand(args);
  if (command == "devices") return streetsim::RunDevicesCommand(args);
  if (command == "serve") return streetsim::RunServeCommand(args);
  if (command == "scenes") return streetsim::RunScenesCommand(args);
  if (command == "jobs") return streetsim::RunJobsCommand(args);
  if (command == "replay") return streetsim::RunReplayCommand(args);
  if (command == "log") return streetsim::RunLogCommand(args);
  if (command == "init") return streetsim::RunInitCommand(args);
  if (command == "train") return streetsim::RunTrainCommand(args);
  if (command == "eval") return streetsim::RunEvalCommand(args);
  if (command == "actors") return streetsim::RunActorsCommand(args);
  std::fprintf(stderr, "streetsim: unknown command '%s' (try streetsim --help)\n", command.c_str());
  return 2;
}
