// A trained scene directory's actors: extracted from its log beside the scene (the end of
// `streetsim train`, and `streetsim actors extract`), and read back for serving.
#pragma once

#include <string>

#include "absl/status/statusor.h"
#include "scene/actors/actor_extraction.h"
#include "scene/actors/actor_set.h"
#include "scene/log/drive_log.h"

namespace streetsim::actors {

// Follows `log`'s moving objects in its LiDAR, extracts the actors of DIR's scene (scene.ply, and
// field.bin when dynamic: the deformed Gaussians at each scan's time) and writes DIR/actors.json
// and actors.ply. FAILED_PRECONDITION when the log has no LiDAR or DIR is a clip set.
absl::StatusOr<ActorSet> ExtractSceneActors(const DriveLog& log, const std::string& dir,
                                            const ActorExtractionOptions& options = {});

}  // namespace streetsim::actors
