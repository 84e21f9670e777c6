// The serving form's cache beside a trained scene (DIR/field.serving, docs/field.md "Serving
// form"): versioned, checksummed and tied by a key to the bytes of the files it was built from
// (scene.ply, field.bin, field_ext.bin) and to the options that shaped it. A cache that does not
// match (another key: the scene was retrained; damaged, truncated, foreign or from another
// version) is never served: LoadOrBuildServingForm rebuilds it from the exact field and says why.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "scene/field/serving_form.h"
#include "scene/field/static_skip.h"

namespace streetsim::field {

inline constexpr char kServingFormFileName[] = "field.serving";

// A key over the bytes of `files` (an absent file counts as absent, so adding field_ext.bin changes
// it) and every option that changes the form. NotFound/DataLoss when a present file cannot be read.
absl::StatusOr<uint64_t> ServingFormSourceKey(const std::vector<std::string>& files, const ServingFormOptions& form,
                                              const StaticSkipOptions& skip);

std::string EncodeServingForm(const ServingForm& form, uint64_t key);
// Errors name `path`: DataLoss for a damaged, truncated or foreign file or another format version;
// FailedPrecondition for a well-formed cache of other sources (key mismatch: stale).
absl::StatusOr<std::unique_ptr<ServingForm>> DecodeServingForm(const std::string& bytes, uint64_t key,
                                                               const std::string& path);

struct CachedServingForm {
  std::unique_ptr<ServingForm> form;
  // The exact scene the form was built from, kept only when the form misses
  // options.max_position_error_m (the caller then serves this instead).
  std::unique_ptr<ServedScene> exact;
  bool from_cache = false;
  std::string note;  // why it was rebuilt or not written (empty: read from the cache)
  bool within_bound(const ServingFormOptions& o) const {
    return form && form->error().position_p99_m <= o.max_position_error_m;
  }
};

// The form in `cache_path` when it holds `key`; else built from make_exact()'s scene (freed again)
// and written atomically to `cache_path` (a cache that cannot be written is a warning: the form is
// served from memory). Errors: make_exact's, Build's.
absl::StatusOr<CachedServingForm> LoadOrBuildServingForm(
    const std::string& cache_path, uint64_t key,
    const std::function<absl::StatusOr<std::unique_ptr<ServedScene>>()>& make_exact,
    const ServingFormOptions& options, ThreadPool& pool);

}  // namespace streetsim::field
