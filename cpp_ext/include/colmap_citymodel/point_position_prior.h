// Direct observation of a 3D point's coordinates (Unger 2020, group f_VT:
// each model vertex is observed with its model coordinates, sigma 0.01 m so
// that the model is "almost fixed").
//
//   residual = L (X - X_obs),   L^T L = Sigma^-1  (L = diag(1/sigma) per axis)
//
// Parameter block: X (3).
#pragma once

#include <Eigen/Core>
#include <ceres/autodiff_cost_function.h>
#include <ceres/ceres.h>

namespace colmap_citymodel {

struct PointPositionPriorCostFunctor {
  PointPositionPriorCostFunctor(const Eigen::Vector3d& observed,
                                const Eigen::Matrix3d& sqrt_information)
      : observed_(observed), sqrt_information_(sqrt_information) {}

  template <typename T>
  bool operator()(const T* const point, T* residuals_ptr) const {
    const Eigen::Matrix<T, 3, 1> diff =
        Eigen::Map<const Eigen::Matrix<T, 3, 1>>(point) - observed_.cast<T>();
    Eigen::Map<Eigen::Matrix<T, 3, 1>> residuals(residuals_ptr);
    residuals = sqrt_information_.cast<T>() * diff;
    return true;
  }

  static ceres::CostFunction* Create(const Eigen::Vector3d& observed,
                                     const Eigen::Matrix3d& sqrt_information) {
    return new ceres::AutoDiffCostFunction<PointPositionPriorCostFunctor, 3, 3>(
        new PointPositionPriorCostFunctor(observed, sqrt_information));
  }

  const Eigen::Vector3d observed_;
  const Eigen::Matrix3d sqrt_information_;
};

}  // namespace colmap_citymodel
