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
               "  devices   list the render backends and Vulkan devices of this machine\n");
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
  std::fprintf(stderr, "streetsim: unknown command '%s' (try streetsim --help)\n", command.c_str());
  return 2;
}
