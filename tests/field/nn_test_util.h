// Gradient-check harness for the extended field's building blocks (scene/field/nn): central
// differences of a double loss over every entry of every parameter block and input, relative L2
// error per group; float-vs-double comparisons.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <functional>
#include <random>
#include <string>
#include <vector>

#include "gtest/gtest.h"
#include "scene/field/nn/nn_layout.h"
#include "scene/field/nn/nn_types.h"

namespace streetsim::field::nn::testing {

inline Mat<double> RandomMat(Eigen::Index rows, Eigen::Index cols, std::mt19937_64& rng, double lo = -1,
                             double hi = 1) {
  std::uniform_real_distribution<double> u(lo, hi);
  Mat<double> m(rows, cols);
  for (Eigen::Index i = 0; i < m.size(); ++i) m.data()[i] = u(rng);
  return m;
}

template <typename T>
std::vector<T> Cast(const std::vector<double>& v) {
  return std::vector<T>(v.begin(), v.end());
}

inline double Dot(const Mat<double>& a, const Mat<double>& b) { return a.cwiseProduct(b).sum(); }

// One group of variables: `size` doubles at `data` (perturbed in place) and their analytic gradient.
struct Var {
  std::string name;
  double* data = nullptr;
  size_t size = 0;
  const double* grad = nullptr;
};

inline std::vector<Var> ParamVars(const NnLayout& layout, std::vector<double>& params,
                                  const std::vector<double>& grad) {
  std::vector<Var> v;
  for (const NnParamBlock& b : layout.blocks())
    v.push_back({b.name, params.data() + b.offset, b.count, grad.data() + b.offset});
  return v;
}

inline Var InputVar(const std::string& name, Mat<double>& x, const Mat<double>& grad) {
  EXPECT_EQ(x.rows(), grad.rows()) << name;
  EXPECT_EQ(x.cols(), grad.cols()) << name;
  return {name, x.data(), static_cast<size_t>(x.size()), grad.data()};
}

// Relative L2 error of each group's analytic gradient against central differences of `loss`.
// An entry whose estimates at two step sizes disagree (a ReLU kink inside the step) is left out
// and counted; the test fails if more than a tenth of a group is left out.
inline void ExpectGradients(const std::string& op, const std::vector<Var>& vars, const std::function<double()>& loss,
                            double tolerance = 1e-6) {
  for (const Var& v : vars) {
    double num = 0, den = 0;
    size_t excluded = 0;
    for (size_t i = 0; i < v.size; ++i) {
      const double x0 = v.data[i];
      auto cd = [&](double h) {
        v.data[i] = x0 + h;
        const double lp = loss();
        v.data[i] = x0 - h;
        const double lm = loss();
        v.data[i] = x0;
        return (lp - lm) / (2 * h);
      };
      const double h = 1e-6 * std::max(1.0, std::abs(x0));
      const double fd1 = cd(h), fd2 = cd(2 * h);
      if (std::abs(fd1 - fd2) > 1e-5 * std::max(1e-3, std::abs(fd1))) {
        ++excluded;
        continue;
      }
      num += (v.grad[i] - fd1) * (v.grad[i] - fd1);
      den += fd1 * fd1;
    }
    const double err = den > 0 ? std::sqrt(num / den) : std::sqrt(num);
    std::printf("[grad] %-12s %-22s n=%5zu excluded=%zu  rel. error %.2e\n", op.c_str(), v.name.c_str(), v.size,
                excluded, err);
    EXPECT_LT(err, tolerance) << op << " " << v.name;
    EXPECT_GT(den, 0) << op << " " << v.name << ": gradient identically zero, the check proves nothing";
    EXPECT_LE(excluded * 10, v.size) << op << " " << v.name;
  }
}

// ||a - b|| / ||b|| for a float result against the double one.
template <typename A, typename B>
double RelDiff(const A* a, const B* b, size_t n) {
  double num = 0, den = 0;
  for (size_t i = 0; i < n; ++i) {
    const double d = static_cast<double>(a[i]) - static_cast<double>(b[i]);
    num += d * d;
    den += static_cast<double>(b[i]) * static_cast<double>(b[i]);
  }
  return den > 0 ? std::sqrt(num / den) : std::sqrt(num);
}

inline void ExpectFloatClose(const std::string& op, const std::string& name, const float* f, const double* d,
                             size_t n, double tolerance = 1e-4) {
  const double err = RelDiff(f, d, n);
  std::printf("[float] %-12s %-22s rel. diff %.2e\n", op.c_str(), name.c_str(), err);
  EXPECT_LT(err, tolerance) << op << " " << name;
}

// Float vs double parameter gradients, per layout block.
inline void ExpectFloatParamsClose(const std::string& op, const NnLayout& layout, const std::vector<float>& f,
                                   const std::vector<double>& d, double tolerance = 1e-4) {
  for (const NnParamBlock& b : layout.blocks())
    ExpectFloatClose(op, b.name, f.data() + b.offset, d.data() + b.offset, b.count, tolerance);
}

inline bool HasNaN(const Mat<double>& m) { return m.array().isNaN().any(); }
inline bool AllFinite(const Mat<double>& m) { return m.array().isFinite().all(); }

}  // namespace streetsim::field::nn::testing
