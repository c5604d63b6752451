// Fictitious observation "distance of a tie point to its face = 0" with the
// face's generalisation error as a random effect shared by its points: an
// offset e0 (m) and tilts e1, e2 (in sigmas of the tilt about the face's two
// principal in-plane axes), each with a prior (PointPositionPriorCost).
//
//   residual = (n^T (X - P0) / |n| + d + e0 + e1 a1^T (X - P0)
//               + e2 a2^T (X - P0)) / (sigma s)
//
// a1, a2: the face's tilt axes scaled by their tilt sigmas (rad), so that a
// point at lever r from P0 moves by e_k a_k^T r along the normal.
// s = |C_a - C_b| / length0, C = R^T (-t) the origin of two frames' rigs: the
// block's scale. After the face's own error, what is left of a tie point's
// distance is the surface's relief and the point's noise, both of a size the
// images fix relative to the block; in metres they shrink with the block,
// which pulls its scale down wherever the faces' offsets are free to follow
// (errors in variables). Measured in the block's units (divided by s) that
// part of the cost does not depend on the scale. With `scaled` false, s = 1.
//
// Parameter blocks: X (3), n (3, ceres::SphereManifold<3>), d (1) as in
// PointPlaneDistanceCost; e (3); rig_from_world (7) of the two frames.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <ceres/autodiff_cost_function.h>
#include <ceres/ceres.h>

#include "colmap_citymodel/point_plane_distance.h"

namespace colmap_citymodel {

struct PointPlaneEffectsDistanceCostFunctor {
  PointPlaneEffectsDistanceCostFunctor(double sigma, const Eigen::Vector3d& reference,
                                       const Eigen::Matrix<double, 2, 3>& tilt_axes,
                                       double length0, bool scaled)
      : inv_sigma_(1.0 / sigma),
        reference_{reference[0], reference[1], reference[2]},
        tilt_axes_(tilt_axes),
        length0_(length0),
        scaled_(scaled) {}

  template <typename T>
  static Eigen::Matrix<T, 3, 1> RigOrigin(const T* const rig_from_world) {
    const Eigen::Map<const Eigen::Quaternion<T>> rotation(rig_from_world);
    const Eigen::Map<const Eigen::Matrix<T, 3, 1>> translation(rig_from_world + 4);
    return rotation.inverse() * (-translation);
  }

  template <typename T>
  bool operator()(const T* const point, const T* const normal,
                  const T* const offset, const T* const effects,
                  const T* const frame_a, const T* const frame_b,
                  T* residuals) const {
    Eigen::Matrix<T, 3, 1> lever;
    for (int i = 0; i < 3; ++i) lever[i] = point[i] - T(reference_[i]);
    const Eigen::Matrix<T, 2, 1> tilts = tilt_axes_.cast<T>() * lever;
    const T distance = SignedDistanceFromReference(point, normal, reference_) +
                       offset[0] + effects[0] + effects[1] * tilts[0] +
                       effects[2] * tilts[1];
    T scale(1.0);
    if (scaled_) {
      scale = (RigOrigin(frame_a) - RigOrigin(frame_b)).norm() / T(length0_);
    }
    residuals[0] = distance * T(inv_sigma_) / scale;
    return true;
  }

  static ceres::CostFunction* Create(double sigma, const Eigen::Vector3d& reference,
                                     const Eigen::Matrix<double, 2, 3>& tilt_axes,
                                     double length0, bool scaled) {
    return new ceres::AutoDiffCostFunction<PointPlaneEffectsDistanceCostFunctor, 1,
                                           3, 3, 1, 3, 7, 7>(
        new PointPlaneEffectsDistanceCostFunctor(sigma, reference, tilt_axes, length0,
                                                 scaled));
  }

  const double inv_sigma_;
  const double reference_[3];
  const Eigen::Matrix<double, 2, 3> tilt_axes_;
  const double length0_;
  const bool scaled_;
};

}  // namespace colmap_citymodel
