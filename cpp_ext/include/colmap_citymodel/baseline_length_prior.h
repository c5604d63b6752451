// Prior on the distance between two positions fixed in two rigs: it holds the block's scale
// where nothing else does. Point-to-plane residuals shrink with the block (a similarity leaves
// every reprojection error unchanged), so with planes on one side only they would set the
// scale against GNSS.
//
//   P_k      = R_k^T (p_k - t_k)                   (position in world, k = a, b)
//   residual = (|P_a - P_b| - length) / sigma
//
// Parameter blocks: rig_from_world of a and of b (7 each) in COLMAP 4's layout,
//   [qx, qy, qz, qw, tx, ty, tz].
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <ceres/autodiff_cost_function.h>
#include <ceres/ceres.h>

namespace colmap_citymodel {

struct BaselineLengthPriorCostFunctor {
  BaselineLengthPriorCostFunctor(double length, double sigma,
                                 const Eigen::Vector3d& position_in_rig_a,
                                 const Eigen::Vector3d& position_in_rig_b)
      : length_(length),
        inverse_sigma_(1.0 / sigma),
        position_in_rig_a_(position_in_rig_a),
        position_in_rig_b_(position_in_rig_b) {}

  template <typename T>
  static Eigen::Matrix<T, 3, 1> Position(const T* const rig_from_world,
                                         const Eigen::Vector3d& position_in_rig) {
    const Eigen::Map<const Eigen::Quaternion<T>> rotation(rig_from_world);
    const Eigen::Map<const Eigen::Matrix<T, 3, 1>> translation(rig_from_world + 4);
    return rotation.inverse() * (position_in_rig.cast<T>() - translation);
  }

  template <typename T>
  bool operator()(const T* const rig_from_world_a, const T* const rig_from_world_b,
                  T* residual) const {
    const Eigen::Matrix<T, 3, 1> baseline =
        Position(rig_from_world_a, position_in_rig_a_) -
        Position(rig_from_world_b, position_in_rig_b_);
    residual[0] = (baseline.norm() - T(length_)) * T(inverse_sigma_);
    return true;
  }

  static ceres::CostFunction* Create(double length, double sigma,
                                     const Eigen::Vector3d& position_in_rig_a,
                                     const Eigen::Vector3d& position_in_rig_b) {
    return new ceres::AutoDiffCostFunction<BaselineLengthPriorCostFunctor, 1, 7, 7>(
        new BaselineLengthPriorCostFunctor(length, sigma, position_in_rig_a,
                                           position_in_rig_b));
  }

  const double length_;
  const double inverse_sigma_;
  const Eigen::Vector3d position_in_rig_a_;
  const Eigen::Vector3d position_in_rig_b_;
};

}  // namespace colmap_citymodel
