// GNSS observation of a position fixed in the rig, with a constant offset of
// the GNSS positions as an unknown (a height offset from another height
// system, or a constant bias common to the whole flight):
//
//   P(rig_from_world) = R^T (p_in_rig - t)      (position in world)
//   residual          = L (P - (P_obs + D b)),  L^T L = Sigma^-1
//
// b (kOffsetSize values) is one parameter block shared by all GNSS priors of
// a block; the constant 3 x kOffsetSize matrix D maps it to world: the unit
// vertical for a height offset (kOffsetSize 1), the identity for a 3D bias
// (kOffsetSize 3). Parameter blocks: rig_from_world (7) in COLMAP 4's layout
// [qx, qy, qz, qw, tx, ty, tz], and b. p_in_rig as in
// projection_center_prior.h (zero, a camera in the rig, or a lever arm).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <ceres/autodiff_cost_function.h>
#include <ceres/ceres.h>

namespace colmap_citymodel {

template <int kOffsetSize>
struct ProjectionCenterOffsetPriorCostFunctor {
  using Directions = Eigen::Matrix<double, 3, kOffsetSize>;

  ProjectionCenterOffsetPriorCostFunctor(const Eigen::Vector3d& observed,
                                         const Eigen::Matrix3d& sqrt_information,
                                         const Eigen::Vector3d& position_in_rig,
                                         const Directions& directions)
      : observed_(observed),
        sqrt_information_(sqrt_information),
        position_in_rig_(position_in_rig),
        directions_(directions) {}

  template <typename T>
  bool operator()(const T* const rig_from_world, const T* const offset_ptr,
                  T* residuals_ptr) const {
    const Eigen::Map<const Eigen::Quaternion<T>> rotation(rig_from_world);
    const Eigen::Map<const Eigen::Matrix<T, 3, 1>> translation(
        rig_from_world + 4);
    const Eigen::Map<const Eigen::Matrix<T, kOffsetSize, 1>> offset(offset_ptr);
    const Eigen::Matrix<T, 3, 1> position =
        rotation.inverse() * (position_in_rig_.cast<T>() - translation);
    const Eigen::Matrix<T, 3, 1> observed =
        observed_.cast<T>() + directions_.template cast<T>() * offset;
    Eigen::Map<Eigen::Matrix<T, 3, 1>> residuals(residuals_ptr);
    residuals = sqrt_information_.cast<T>() * (position - observed);
    return true;
  }

  static ceres::CostFunction* Create(const Eigen::Vector3d& observed,
                                     const Eigen::Matrix3d& sqrt_information,
                                     const Eigen::Vector3d& position_in_rig,
                                     const Directions& directions) {
    return new ceres::AutoDiffCostFunction<ProjectionCenterOffsetPriorCostFunctor,
                                           3, 7, kOffsetSize>(
        new ProjectionCenterOffsetPriorCostFunctor(observed, sqrt_information,
                                                   position_in_rig, directions));
  }

  const Eigen::Vector3d observed_;
  const Eigen::Matrix3d sqrt_information_;
  const Eigen::Vector3d position_in_rig_;
  const Directions directions_;
};

}  // namespace colmap_citymodel
