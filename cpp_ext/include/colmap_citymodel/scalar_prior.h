// Direct observation of one scalar unknown (used for the prior of a plane's
// generalisation offset, o ~ N(0, sigma_generalisation^2)).
//
//   residual = (x - x_obs) / sigma
//
// Parameter block: x (1).
#pragma once

#include <ceres/autodiff_cost_function.h>
#include <ceres/ceres.h>

namespace colmap_citymodel {

struct ScalarPriorCostFunctor {
  ScalarPriorCostFunctor(double observed, double sigma)
      : observed_(observed), inv_sigma_(1.0 / sigma) {}

  template <typename T>
  bool operator()(const T* const value, T* residuals) const {
    residuals[0] = (value[0] - T(observed_)) * T(inv_sigma_);
    return true;
  }

  static ceres::CostFunction* Create(double observed, double sigma) {
    return new ceres::AutoDiffCostFunction<ScalarPriorCostFunctor, 1, 1>(
        new ScalarPriorCostFunctor(observed, sigma));
  }

  const double observed_;
  const double inv_sigma_;
};

}  // namespace colmap_citymodel
