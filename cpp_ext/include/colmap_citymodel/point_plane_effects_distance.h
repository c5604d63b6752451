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
#include <ceres/ceres.h>
#include <ceres/jet.h>
#include <ceres/sized_cost_function.h>

#include "colmap_citymodel/point_plane_distance.h"

namespace colmap_citymodel {

// The residual and its Jacobians in closed form (the distance and the effects)
// and by forward differentiation of each frame's rig origin alone (7 values):
// automatic differentiation of the whole residual would carry all 24
// parameters through every operation, and these residuals, one per tie point
// of a face with effects, are evaluated in every Ceres iteration.
class PointPlaneEffectsDistanceCost
    : public ceres::SizedCostFunction<1, 3, 3, 1, 3, 7, 7> {
 public:
  PointPlaneEffectsDistanceCost(double sigma, const Eigen::Vector3d& reference,
                                const Eigen::Matrix<double, 2, 3>& tilt_axes,
                                double length0, bool scaled)
      : inv_sigma_(1.0 / sigma),
        reference_(reference),
        tilt_axes_(tilt_axes),
        length0_(length0),
        scaled_(scaled) {}

  // The origin of a rig, C = R^T (-t), as Eigen's quaternion rotates (the
  // rotation's inverse applied to -t).
  template <typename T>
  static Eigen::Matrix<T, 3, 1> RigOrigin(const T* const rig_from_world) {
    const Eigen::Map<const Eigen::Quaternion<T>> rotation(rig_from_world);
    const Eigen::Map<const Eigen::Matrix<T, 3, 1>> translation(rig_from_world + 4);
    return rotation.inverse() * (-translation);
  }

  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    const Eigen::Map<const Eigen::Vector3d> point(parameters[0]);
    const Eigen::Map<const Eigen::Vector3d> normal(parameters[1]);
    const double offset = parameters[2][0];
    const double* const effects = parameters[3];
    const Eigen::Vector3d lever = point - reference_;
    const Eigen::Vector2d tilts = tilt_axes_ * lever;
    const double norm = normal.norm();
    const double along = normal.dot(lever) / norm;
    const double distance = along + offset + effects[0] + effects[1] * tilts[0] +
                            effects[2] * tilts[1];
    double scale = 1.0;
    Eigen::Matrix<double, 1, 7> scale_a = Eigen::Matrix<double, 1, 7>::Zero();
    Eigen::Matrix<double, 1, 7> scale_b = Eigen::Matrix<double, 1, 7>::Zero();
    if (scaled_) {
      const bool frames = jacobians != nullptr &&
                          (jacobians[4] != nullptr || jacobians[5] != nullptr);
      scale = Scale(parameters[4], parameters[5], frames ? &scale_a : nullptr,
                    frames ? &scale_b : nullptr);
    }
    const double factor = inv_sigma_ / scale;
    residuals[0] = distance * factor;
    if (jacobians == nullptr) return true;
    if (jacobians[0] != nullptr) {
      Eigen::Map<Eigen::RowVector3d> d_point(jacobians[0]);
      d_point = factor * (normal / norm + effects[1] * tilt_axes_.row(0).transpose() +
                    effects[2] * tilt_axes_.row(1).transpose())
                       .transpose();
    }
    if (jacobians[1] != nullptr) {
      Eigen::Map<Eigen::RowVector3d> d_normal(jacobians[1]);
      d_normal = factor * ((lever - along * normal / norm) / norm).transpose();
    }
    if (jacobians[2] != nullptr) jacobians[2][0] = factor;
    if (jacobians[3] != nullptr) {
      jacobians[3][0] = factor;
      jacobians[3][1] = factor * tilts[0];
      jacobians[3][2] = factor * tilts[1];
    }
    // r = distance / (sigma s): dr/ds = -r / s.
    const double by_scale = -residuals[0] / scale;
    if (jacobians[4] != nullptr) {
      Eigen::Map<Eigen::Matrix<double, 1, 7>> d_frame_a(jacobians[4]);
      d_frame_a = by_scale * scale_a;
    }
    if (jacobians[5] != nullptr) {
      Eigen::Map<Eigen::Matrix<double, 1, 7>> d_frame_b(jacobians[5]);
      d_frame_b = by_scale * scale_b;
    }
    return true;
  }

 private:
  // s = |C_a - C_b| / length0 and, where asked, its derivatives by each
  // frame's 7 parameters.
  double Scale(const double* frame_a, const double* frame_b,
               Eigen::Matrix<double, 1, 7>* d_a,
               Eigen::Matrix<double, 1, 7>* d_b) const {
    if (d_a == nullptr) {
      return (RigOrigin(frame_a) - RigOrigin(frame_b)).norm() / length0_;
    }
    using Jet = ceres::Jet<double, 7>;
    Jet a[7], b[7];
    for (int i = 0; i < 7; ++i) {
      a[i] = Jet(frame_a[i], i);
      b[i] = Jet(frame_b[i], i);
    }
    const Eigen::Matrix<Jet, 3, 1> origin_a = RigOrigin(a);
    const Eigen::Matrix<Jet, 3, 1> origin_b = RigOrigin(b);
    Eigen::Vector3d between, direction;
    for (int k = 0; k < 3; ++k) between[k] = origin_a[k].a - origin_b[k].a;
    const double length = between.norm();
    direction = between / (length * length0_);
    d_a->setZero();
    d_b->setZero();
    for (int k = 0; k < 3; ++k) {
      *d_a += direction[k] * origin_a[k].v.transpose();
      *d_b -= direction[k] * origin_b[k].v.transpose();
    }
    return length / length0_;
  }

  const double inv_sigma_;
  const Eigen::Vector3d reference_;
  const Eigen::Matrix<double, 2, 3> tilt_axes_;
  const double length0_;
  const bool scaled_;
};

}  // namespace colmap_citymodel
