// GNSS observation of a position fixed in the rig (Unger 2020, group f_pos):
// the projection centre of a camera, or a GNSS antenna with a lever arm.
//
//   P(rig_from_world) = R^T (p_in_rig - t)      (position in world)
//   residual          = L (P - P_obs),          L^T L = Sigma^-1
//
// Parameter block: rig_from_world (7) in COLMAP 4's layout,
//   [qx, qy, qz, qw, tx, ty, tz]  (Eigen quaternion order, as Rigid3d::params;
//   COLMAP puts it on a product of EigenQuaternionManifold and R^3).
// p_in_rig is constant: zero for the rig origin (= the camera of a
// single-camera rig), the camera centre in the rig for another sensor
// (-R_cam_from_rig^T t_cam_from_rig), or a GNSS lever arm.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <ceres/autodiff_cost_function.h>
#include <ceres/ceres.h>

namespace colmap_citymodel {

struct ProjectionCenterPriorCostFunctor {
  ProjectionCenterPriorCostFunctor(const Eigen::Vector3d& observed,
                                   const Eigen::Matrix3d& sqrt_information,
                                   const Eigen::Vector3d& position_in_rig)
      : observed_(observed),
        sqrt_information_(sqrt_information),
        position_in_rig_(position_in_rig) {}

  template <typename T>
  bool operator()(const T* const rig_from_world, T* residuals_ptr) const {
    const Eigen::Map<const Eigen::Quaternion<T>> rotation(rig_from_world);
    const Eigen::Map<const Eigen::Matrix<T, 3, 1>> translation(
        rig_from_world + 4);
    // inverse() rather than conjugate(): exact also for a slightly
    // non-unit quaternion, like COLMAP's own position prior.
    const Eigen::Matrix<T, 3, 1> position =
        rotation.inverse() * (position_in_rig_.cast<T>() - translation);
    Eigen::Map<Eigen::Matrix<T, 3, 1>> residuals(residuals_ptr);
    residuals = sqrt_information_.cast<T>() * (position - observed_.cast<T>());
    return true;
  }

  static ceres::CostFunction* Create(const Eigen::Vector3d& observed,
                                     const Eigen::Matrix3d& sqrt_information,
                                     const Eigen::Vector3d& position_in_rig) {
    return new ceres::
        AutoDiffCostFunction<ProjectionCenterPriorCostFunctor, 3, 7>(
            new ProjectionCenterPriorCostFunctor(
                observed, sqrt_information, position_in_rig));
  }

  const Eigen::Vector3d observed_;
  const Eigen::Matrix3d sqrt_information_;
  const Eigen::Vector3d position_in_rig_;
};

}  // namespace colmap_citymodel
