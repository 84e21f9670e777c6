// The streetsim command-line tool.
#include <cstdio>
#include <cstring>
#include <string>
#include <vector>

#include "client/cli/commands.h"

namespace {

void PrintUsage(FILE* out) {
  std::fprintf(out,
               "usage: streetsim <command> [flags]\n"
               "\n"
               "commands:\n"
               "  render    render a Gaussian scene from a camera:\n"
               "            streetsim render --ply SCENE.ply --camera CAMERA.json --out-rgb OUT.png\n"
               "              [--out-depth D.tiff] [--out-alpha A.tiff] [--background R,G,B]\n"
               "              [--backend auto|cpu|vulkan]\n"
               "  ply-info  print a scene's size, SH degree and bounds; optionally write a camera\n"
               "            that frames it: streetsim ply-info SCENE.ply [--camera-out CAMERA.json]\n"
               "              [--width W] [--height H] [--view front|back|left|right|top]\n"
               "  devices   list the render backends and Vulkan devices of this machine\n"
               "  log       inspect a driving log (KITTI raw/odometry, COLMAP; docs/logs.md):\n"
               "            streetsim log info PATH\n"
               "            streetsim log preview PATH --frame N --out F.png [--camera NAME] [--max-depth M]\n"
               "            streetsim log poses PATH [--from-lidar] [--frames A:B] [--out POSES.txt]\n"
               "            streetsim log camera PATH --frame N --out CAMERA.json [--camera NAME]\n"
               "  init      initial Gaussians of a log: streetsim init PATH --out SCENE.ply [--frames A:B[:S]]\n"
               "              [--voxel M] [--max-range M] [--sky] [--drop-dynamic] [--random-points N]\n"
               "  serve     run the gRPC simulator server (docs/server.md): streetsim serve\n"
               "              [--listen HOST:PORT] [--data-root DIR] [--state-dir DIR] [--backend B]\n"
               "              [--field-device auto|cpu|vulkan] ...\n"
               "  scenes    list a server's scenes: streetsim scenes --server HOST:PORT\n"
               "  jobs      training jobs on a server: streetsim jobs list|train|watch|get|cancel ...\n"
               "  replay    scripted replay through a server: streetsim replay SCENARIO.json\n"
               "  train     scene training (docs/training.md): streetsim train --log PATH --out DIR\n"
               "              [--iterations N] [--resolution-scale S] [--holdout-every K] [--seed K] [--resume]\n"
               "              [--checkpoint-every N] [--no-sky] [--exposure] [--no-depth] [--deterministic]\n"
               "              [--lidar-weight W] [--lidar-every K] [--no-lidar-loss] [--backend cpu|vulkan|auto]\n"
               "              [--field static|s3gaussian|extended] [--static-iterations N] [--field-modules LIST]\n"
               "              [--field-device auto|cpu|vulkan] [--field-init zero-heads|spec] [--clip-frames N]\n"
               "              (default field: s3gaussian when --iterations > the 5000-iteration warm-up, else static)\n"
               "  eval      metrics of a trained scene: streetsim eval --scene DIR --log PATH [--split test|train] [--no-lidar]\n"
               "              [--decomposition DIR] [--video OUT.avi|OUT.mp4] [--video-fps F]\n"
               "              [--holdout-every K]   (JSON on stdout, a table on stderr)\n");
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2 || !std::strcmp(argv[1], "--help") || !std::strcmp(argv[1], "-h") ||
      !std::strcmp(argv[1], "help")) {
    PrintUsage(argc < 2 ? stderr : stdout);
    return argc < 2 ? 2 : 0;
  }
  const std::string command = argv[1];
  const std::vector<std::string> args(argv + 2, argv + argc);
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
  std::fprintf(stderr, "streetsim: unknown command '%s' (try streetsim --help)\n", command.c_str());
  return 2;
}
