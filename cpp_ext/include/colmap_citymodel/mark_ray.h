// A ground mark measured in an image (a ground control point's image
// observation): the mark's point X seen through the frame's pose, compared
// with the measured pixel in the normalised image plane of the camera.
//
//   X_rig  = R_rig_from_world X + t_rig_from_world
//   X_cam  = R_cam_from_rig X_rig + t_cam_from_rig          (constant sensor)
//   residual = (f / sigma) (X_cam.xy / X_cam.z - m)
//
// m is the measured pixel undistorted into the normalised image plane with
// the camera's current intrinsics (pycolmap Camera.cam_from_img), f the
// camera's mean focal length in pixels, so the residual is in pixels at the
// image centre (exact for a pinhole camera, to the distortion's local scale
// otherwise) over the measurement's sigma in pixels. The intrinsics stay out
// of this residual: a few marks say nothing about them beside the tie points.
//
// Parameter blocks: X (3), rig_from_world (7) in COLMAP 4's layout
//   [qx, qy, qz, qw, tx, ty, tz] (Rigid3d::params).
// A point behind the camera makes the residual fail (Ceres rejects the step).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <ceres/autodiff_cost_function.h>
#include <ceres/ceres.h>

namespace colmap_citymodel {

struct MarkRayCostFunctor {
  MarkRayCostFunctor(const Eigen::Vector2d& normalised,
                     double scale,
                     const Eigen::Quaterniond& cam_from_rig_rotation,
                     const Eigen::Vector3d& cam_from_rig_translation)
      : normalised_(normalised),
        scale_(scale),
        cam_from_rig_rotation_(cam_from_rig_rotation),
        cam_from_rig_translation_(cam_from_rig_translation) {}

  template <typename T>
  bool operator()(const T* const point,
                  const T* const rig_from_world,
                  T* residuals) const {
    const Eigen::Map<const Eigen::Quaternion<T>> rotation(rig_from_world);
    const Eigen::Map<const Eigen::Matrix<T, 3, 1>> translation(
        rig_from_world + 4);
    const Eigen::Map<const Eigen::Matrix<T, 3, 1>> x(point);
    const Eigen::Matrix<T, 3, 1> in_rig = rotation * x + translation;
    const Eigen::Matrix<T, 3, 1> in_cam =
        cam_from_rig_rotation_.cast<T>() * in_rig +
        cam_from_rig_translation_.cast<T>();
    if (!(in_cam(2) > T(0))) {
      return false;
    }
    residuals[0] = T(scale_) * (in_cam(0) / in_cam(2) - T(normalised_(0)));
    residuals[1] = T(scale_) * (in_cam(1) / in_cam(2) - T(normalised_(1)));
    return true;
  }

  static ceres::CostFunction* Create(
      const Eigen::Vector2d& normalised,
      double scale,
      const Eigen::Quaterniond& cam_from_rig_rotation,
      const Eigen::Vector3d& cam_from_rig_translation) {
    return new ceres::AutoDiffCostFunction<MarkRayCostFunctor, 2, 3, 7>(
        new MarkRayCostFunctor(normalised, scale, cam_from_rig_rotation,
                               cam_from_rig_translation));
  }

  const Eigen::Vector2d normalised_;
  const double scale_;
  const Eigen::Quaterniond cam_from_rig_rotation_;
  const Eigen::Vector3d cam_from_rig_translation_;
};

}  // namespace colmap_citymodel
