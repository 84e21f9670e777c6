// The presets' JSON files (scene/train/presets/*.json), built into the binary by CMake so that a
// preset is found wherever the binary runs (they are also installed under share/streetsim/presets
// for reading).
#pragma once

#include <string>
#include <utility>
#include <vector>

namespace streetsim::train::config {

// (name, file text) per preset, in the order help lists them.
const std::vector<std::pair<std::string, std::string>>& PresetFiles();

}  // namespace streetsim::train::config
