// Fictitious observation "distance of a point to a plane = 0" (Unger 2020,
// eq. 5; observation groups f_dTP for tie points and f_dVT for model vertices).
//
//   residual = (n^T X / |n| + d) / sigma
//
// Parameter blocks:
//   X (3): the point (a COLMAP point3D xyz block, or a model vertex block),
//   n (3): plane normal, kept unit length by ceres::SphereManifold<3>,
//   d (1): plane offset, so that n^T X + d = 0 on the plane.
// The plane thus has 3 degrees of freedom (2 on the sphere + 1 offset),
// equivalent to Unger's minimal (alpha, beta, delta) update. Dividing by |n|
// keeps the residual a metric distance even if the normal drifts off the unit
// sphere (it does not on the manifold, but the cost stays well defined).
#pragma once

#include <ceres/autodiff_cost_function.h>
#include <ceres/ceres.h>

namespace colmap_citymodel {

struct PointPlaneDistanceCostFunctor {
  explicit PointPlaneDistanceCostFunctor(double sigma)
      : inv_sigma_(1.0 / sigma) {}

  template <typename T>
  bool operator()(const T* const point,
                  const T* const normal,
                  const T* const offset,
                  T* residuals) const {
    const T norm = ceres::sqrt(normal[0] * normal[0] + normal[1] * normal[1] +
                               normal[2] * normal[2]);
    const T dot = normal[0] * point[0] + normal[1] * point[1] +
                  normal[2] * point[2];
    residuals[0] = (dot / norm + offset[0]) * T(inv_sigma_);
    return true;
  }

  static ceres::CostFunction* Create(double sigma) {
    return new ceres::
        AutoDiffCostFunction<PointPlaneDistanceCostFunctor, 1, 3, 3, 1>(
            new PointPlaneDistanceCostFunctor(sigma));
  }

  const double inv_sigma_;
};

}  // namespace colmap_citymodel
