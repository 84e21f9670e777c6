// The field's float results must not depend on where the heap puts the buffers (docs/training.md
// "Reproducibility"): FieldBackward once summed bias gradients in an order that followed the
// runtime alignment of its per-thread scratch, so identical --deterministic runs differed in the
// last bit across processes. Here one process moves every operator-new block by 16..64 bytes
// (mod 64) instead: a replacement operator new, so this test has a binary of its own.
#include <atomic>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <new>
#include <random>
#include <vector>

#include "gtest/gtest.h"
#include "render/common/thread_pool.h"
#include "scene/field/nn/linear.h"
#include "tests/field/field_test_util.h"

namespace {
// Offset of the next operator-new blocks from a 64-byte boundary: 16, 32, 48 or 64.
std::atomic<size_t> g_new_shift{64};
}  // namespace

void* operator new(std::size_t n) {
  const size_t shift = g_new_shift.load(std::memory_order_relaxed);
  char* raw = static_cast<char*>(std::malloc(n + 160));
  if (!raw) throw std::bad_alloc();
  char* p = reinterpret_cast<char*>((reinterpret_cast<uintptr_t>(raw) + 63) & ~uintptr_t{63}) + shift;
  reinterpret_cast<char**>(p)[-1] = raw;  // shift >= 16: the slot lies inside the block
  return p;
}
void* operator new[](std::size_t n) { return ::operator new(n); }
void* operator new(std::size_t n, const std::nothrow_t&) noexcept {
  try {
    return ::operator new(n);
  } catch (...) {
    return nullptr;
  }
}
void* operator new[](std::size_t n, const std::nothrow_t& t) noexcept { return ::operator new(n, t); }
void operator delete(void* p) noexcept {
  if (p) std::free(reinterpret_cast<char**>(p)[-1]);
}
void operator delete[](void* p) noexcept { ::operator delete(p); }
void operator delete(void* p, std::size_t) noexcept { ::operator delete(p); }
void operator delete[](void* p, std::size_t) noexcept { ::operator delete(p); }
void operator delete(void* p, const std::nothrow_t&) noexcept { ::operator delete(p); }
void operator delete[](void* p, const std::nothrow_t&) noexcept { ::operator delete(p); }

namespace streetsim::field {
namespace {

struct Result {
  std::vector<float> dx, dsh, d_params, d_means;
};

// Forward and backward with every std::vector / new block `shift` bytes past a 64-byte boundary.
Result RunWithHeapShift(const FieldConfig& c, size_t shift) {
  g_new_shift = shift;
  const FieldLayout L = FieldLayout::Make(c);
  const std::vector<float> params = testing::RandomParams<float>(c, L, 11);
  constexpr size_t kN = 333;  // not a multiple of the 64-row chunks
  const std::vector<float> means = testing::RandomMeans<float>(kN, 5, 12);
  std::mt19937_64 rng(13);
  std::uniform_real_distribution<float> u(-1, 1);
  std::vector<float> g_dx(kN * 3), g_dsh(kN * kShOutputs);
  for (float& v : g_dx) v = u(rng);
  for (float& v : g_dsh) v = u(rng);
  ThreadPool pool(1);
  auto ws = std::make_unique<FieldWorkspace>();
  Result r;
  r.dx.resize(kN * 3);
  r.dsh.resize(kN * kShOutputs);
  r.d_params.assign(L.total, 0.0f);
  r.d_means.assign(kN * 3, 0.0f);
  const FieldQuery q = testing::TestQuery(0.3);
  FieldForward<float>(L, params.data(), q, means.data(), nullptr, kN, r.dx.data(), r.dsh.data(), pool, *ws);
  FieldBackward<float>(L, params.data(), q, means.data(), kN, g_dx.data(), g_dsh.data(), r.d_params.data(),
                       r.d_means.data(), pool, *ws);
  g_new_shift = 64;
  return r;
}

void ExpectSameBits(const std::vector<float>& a, const std::vector<float>& b, const char* what, size_t shift) {
  ASSERT_EQ(a.size(), b.size()) << what;
  size_t differ = 0, first = a.size();
  for (size_t i = 0; i < a.size(); ++i) {
    if (std::memcmp(&a[i], &b[i], sizeof(float)) != 0) {
      if (differ++ == 0) first = i;
    }
  }
  EXPECT_EQ(differ, 0u) << what << " with blocks at 64k + " << shift << ": " << differ << " values differ, first at "
                        << first << " (" << a[first] << " vs " << b[first] << ")";
}

void ExpectSameBitsForAllShifts(const FieldConfig& c) {
  const Result ref = RunWithHeapShift(c, 64);
  for (size_t shift : {16, 32, 48}) {
    const Result r = RunWithHeapShift(c, shift);
    ExpectSameBits(ref.dx, r.dx, "dx", shift);
    ExpectSameBits(ref.dsh, r.dsh, "dsh", shift);
    ExpectSameBits(ref.d_params, r.d_params, "d_params", shift);
    ExpectSameBits(ref.d_means, r.d_means, "d_means", shift);
  }
}

TEST(FieldBits, BackwardDoesNotDependOnHeapAddresses) {
  FieldConfig c = testing::SmallConfig();
  c.width = 16;  // two AVX packets per bias row: the peeled and the vectorised columns both occur
  ExpectSameBitsForAllShifts(c);
}

// The spec's channel count and MLP width (channel reductions of 32, bias rows of 64), small grids.
TEST(FieldBits, SpecWidthsDoNotDependOnHeapAddresses) {
  FieldConfig c;
  c.base_resolution = 8;
  c.multires = {1, 2};
  c.time_resolution = 6;
  ExpectSameBitsForAllShifts(c);
}

// The extended field's building blocks accumulate bias gradients the same way (nn::AddColumnSums).
std::vector<float> LinearGradWithHeapShift(size_t shift) {
  g_new_shift = shift;
  nn::LinearSpec s;
  s.in = 16;
  s.out = 24;
  s.b_offset = static_cast<size_t>(s.in) * s.out;
  std::mt19937_64 rng(21);
  std::vector<float> params(s.b_offset + s.out);
  nn::InitLinear(s, rng, params.data());
  std::uniform_real_distribution<float> u(-1, 1);
  nn::Mat<float> x(101, s.in), dy(101, s.out);
  for (Eigen::Index i = 0; i < x.size(); ++i) x.data()[i] = u(rng);
  for (Eigen::Index i = 0; i < dy.size(); ++i) dy.data()[i] = u(rng);
  std::vector<float> d_params(params.size(), 0.0f);
  EXPECT_TRUE(nn::LinearGrad<float>(s, params.data(), x, dy, nullptr, false, d_params.data()).ok());
  g_new_shift = 64;
  return d_params;
}

TEST(FieldBits, LinearGradDoesNotDependOnHeapAddresses) {
  const std::vector<float> ref = LinearGradWithHeapShift(64);
  for (size_t shift : {16, 32, 48}) ExpectSameBits(ref, LinearGradWithHeapShift(shift), "linear d_params", shift);
}

}  // namespace
}  // namespace streetsim::field
