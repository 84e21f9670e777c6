// streetsim subcommands. Each returns the process exit code: 0 success, 1 runtime failure,
// 2 bad arguments; errors are one line on stderr.
#pragma once

#include <string>
#include <vector>

namespace streetsim {

int RunRenderCommand(const std::vector<std::string>& args);
int RunLidarRenderCommand(const std::vector<std::string>& args);  // render --lidar (docs/lidar.md)
int RunPlyInfoCommand(const std::vector<std::string>& args);
int RunDevicesCommand(const std::vector<std::string>& args);

// Server and remote commands (docs/server.md).
int RunServeCommand(const std::vector<std::string>& args);
int RunScenesCommand(const std::vector<std::string>& args);
int RunJobsCommand(const std::vector<std::string>& args);
int RunRemoteRenderCommand(const std::vector<std::string>& args);  // render --server
int RunReplayCommand(const std::vector<std::string>& args);
int RunLogCommand(const std::vector<std::string>& args);  // log info|preview|poses|camera|tracks
int RunInitCommand(const std::vector<std::string>& args);
int RunTrainCommand(const std::vector<std::string>& args);
int RunEvalCommand(const std::vector<std::string>& args);
int RunActorsCommand(const std::vector<std::string>& args);  // actors extract|list (docs/actors.md)

}  // namespace streetsim
