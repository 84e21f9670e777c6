// Forward and backward passes of the deformation field on the cpu, batched over Gaussians
// (spec 3.1-3.3): HexPlane features (bilinear, align_corners, border clamp; product over the 6
// planes, concatenation over levels), the 128 -> 64 trunk and the Δposition / ΔSH heads.
//
// Templated on the scalar: float for training and serving, double as the gradient-check reference.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <vector>

#include "render/common/thread_pool.h"
#include "scene/field/field_config.h"

namespace streetsim::field {

// Where the field is queried: the AABB that normalises positions and the time coordinate on the
// time axis of the planes (already mapped, see DeformationField::TimeCoordinate).
struct FieldQuery {
  double aabb_min[3] = {-1, -1, -1};
  double aabb_max[3] = {1, 1, 1};
  double time_coord = 0;  // in [-1, 1]; clamped by the border rule like every coordinate
};

// Reusable scratch of the passes (per-thread activations, backward block buffers), so that a
// training step allocates nothing after the first. One per caller; not shared between threads.
class FieldWorkspace {
 public:
  FieldWorkspace();
  ~FieldWorkspace();
  struct Impl;
  Impl& impl() { return *impl_; }

  // Wall time of the last FieldBackward's two phases (bench/field_bench): per-row work (sampling,
  // MLP forward and backward, dL/d(sample), dL/d(position)) and the per-plane scatter.
  double last_rows_ms = 0, last_scatter_ms = 0;
  // DeformBackward's dL/dΔx, dL/dΔSH (kept to avoid page faults every step).
  std::vector<float> d_dx, d_dsh;

 private:
  std::unique_ptr<Impl> impl_;
};

// Δposition [n*3] and ΔSH [n*48] (ΔSH[k][c] at 3k + c, k = 0 the DC term) of the Gaussians at
// `means` (world metres). With `rows` non-null, output row r belongs to Gaussian rows[r] of
// `means` (the serving path evaluates only dynamic Gaussians); outputs are compact. `dsh` may be
// null (ΔSH not wanted).
template <typename T>
void FieldForward(const FieldLayout& layout, const T* params, const FieldQuery& query, const T* means,
                  const uint32_t* rows, size_t n, T* dx, T* dsh, ThreadPool& pool, FieldWorkspace& ws);

// The serving shortcut: the spatial planes (xy, xz, yz) do not depend on time, so their product
// per level can be computed once per Gaussian (`spatial` [n * feature_dim], row r for output row
// r) and every later timestamp samples only the space-time planes (a few cached rows of them).
// Equal to FieldForward up to float rounding (the product's order differs).
template <typename T>
void SpatialFeatures(const FieldLayout& layout, const T* params, const FieldQuery& query, const T* means,
                     const uint32_t* rows, size_t n, T* spatial, ThreadPool& pool);
template <typename T>
void FieldForwardCached(const FieldLayout& layout, const T* params, const FieldQuery& query, const T* means,
                        const uint32_t* rows, const T* spatial, size_t n, T* dx, T* dsh, ThreadPool& pool,
                        FieldWorkspace& ws);

// Given dL/dΔposition [n*3] and dL/dΔSH [n*48] (null = zero) of the Gaussians at `means` (all of
// them, no row list), adds dL/d(field parameters) to d_params [layout.total] and dL/d(means)
// through the field (the plane sampling depends on position) to d_means [n*3] (null: not wanted).
// Plane gradients are scattered per plane after each block of Gaussians, one thread per plane, so
// the grid gradient is identical for any thread count; MLP gradients are summed per thread.
template <typename T>
void FieldBackward(const FieldLayout& layout, const T* params, const FieldQuery& query, const T* means, size_t n,
                   const T* d_dx, const T* d_dsh, T* d_params, T* d_means, ThreadPool& pool, FieldWorkspace& ws);

}  // namespace streetsim::field
