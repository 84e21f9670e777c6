// Initial Gaussian scales as 3DGS sets them: the root of the mean squared distance to the three
// nearest other points, isotropic, as a log-scale.
#pragma once

#include <vector>

#include <Eigen/Core>

namespace streetsim {

// One log-scale per point. max_scale_m caps isolated points (a lone far point would otherwise
// become a huge blob covering the image).
std::vector<float> KnnLogScales(const std::vector<Eigen::Vector3f>& points, int k = 3,
                                double max_scale_m = 2.0);

}  // namespace streetsim
