// Fictitious observation "distance of a tie point to its plane = 0" with a
// per-plane generalisation offset (Unger 2020 6.3: generalisation
// errors are systematic per plane, so independent f_dTP sigmas make the a
// posteriori precision over-optimistic).
//
//   residual = (n^T (X - P0) / |n| + d + o) / sigma
//
// Parameter blocks:
//   X (3): the tie point (a COLMAP point3D xyz block),
//   n (3): plane normal (ceres::SphereManifold<3>), d (1): plane offset at the
//          reference point P0, as in PointPlaneDistanceCost; the model plane
//          is n^T (X - P0) + d = 0,
//   o (1): the plane's generalisation offset: the surface the tie points lie
//          on is n^T X + d + o = 0. One o per plane, shared by all its tie
//          points, with a prior o ~ N(0, sigma_generalisation^2)
//          (ScalarPriorCost), so that the plane's systematic deviation does
//          not average out with the number of its points.
#pragma once

#include <ceres/autodiff_cost_function.h>
#include <ceres/ceres.h>

#include "colmap_citymodel/point_plane_distance.h"

namespace colmap_citymodel {

struct PointPlaneOffsetDistanceCostFunctor {
  PointPlaneOffsetDistanceCostFunctor(double sigma, const double* reference)
      : inv_sigma_(1.0 / sigma),
        reference_{reference[0], reference[1], reference[2]} {}

  template <typename T>
  bool operator()(const T* const point,
                  const T* const normal,
                  const T* const offset,
                  const T* const generalisation,
                  T* residuals) const {
    residuals[0] = (SignedDistanceFromReference(point, normal, reference_) +
                    offset[0] + generalisation[0]) *
                   T(inv_sigma_);
    return true;
  }

  static ceres::CostFunction* Create(double sigma,
                                     const double* reference) {
    return new ceres::AutoDiffCostFunction<PointPlaneOffsetDistanceCostFunctor,
                                           1, 3, 3, 1, 1>(
        new PointPlaneOffsetDistanceCostFunctor(sigma, reference));
  }

  const double inv_sigma_;
  const double reference_[3];
};

}  // namespace colmap_citymodel
