// Fictitious observation "distance of a point to a plane = 0" (Unger 2020,
// eq. 5; observation groups f_dTP for tie points and f_dVT for model vertices).
//
//   residual = (n^T (X - P0) / |n| + d) / sigma
//
// Parameter blocks:
//   X (3): the point (a COLMAP point3D xyz block, or a model vertex block),
//   n (3): plane normal, kept unit length by ceres::SphereManifold<3>,
//   d (1): plane offset at the plane's reference point P0 (a constant, e.g. the
//          face centroid), so that n^T (X - P0) + d = 0 on the plane.
// P0 on the plane keeps n and d uncorrelated (Unger eq. 5 rotates about P0 as
// well): with P0 at the origin of a frame hundreds of metres away, a tilt of n
// moves the plane by the lever arm and the two unknowns are nearly dependent,
// which made Levenberg-Marquardt crawl (190 iterations) on small detailed faces.
// The plane thus has 3 degrees of freedom (2 on the sphere + 1 offset),
// equivalent to Unger's minimal (alpha, beta, delta) update. Dividing by |n|
// keeps the residual a metric distance even if the normal drifts off the unit
// sphere (it does not on the manifold, but the cost stays well defined).
#pragma once

#include <ceres/autodiff_cost_function.h>
#include <ceres/ceres.h>

namespace colmap_citymodel {

// n^T (X - P0) / |n|: the signed distance of X from the plane through P0 with
// normal n, shared by the point-plane costs.
template <typename T>
T SignedDistanceFromReference(const T* const point, const T* const normal,
                              const double* const reference) {
  const T norm = ceres::sqrt(normal[0] * normal[0] + normal[1] * normal[1] +
                             normal[2] * normal[2]);
  const T dot = normal[0] * (point[0] - T(reference[0])) +
                normal[1] * (point[1] - T(reference[1])) +
                normal[2] * (point[2] - T(reference[2]));
  return dot / norm;
}

struct PointPlaneDistanceCostFunctor {
  PointPlaneDistanceCostFunctor(double sigma, const double* reference)
      : inv_sigma_(1.0 / sigma),
        reference_{reference[0], reference[1], reference[2]} {}

  template <typename T>
  bool operator()(const T* const point,
                  const T* const normal,
                  const T* const offset,
                  T* residuals) const {
    residuals[0] =
        (SignedDistanceFromReference(point, normal, reference_) + offset[0]) *
        T(inv_sigma_);
    return true;
  }

  static ceres::CostFunction* Create(double sigma,
                                     const double* reference) {
    return new ceres::
        AutoDiffCostFunction<PointPlaneDistanceCostFunctor, 1, 3, 3, 1>(
            new PointPlaneDistanceCostFunctor(sigma, reference));
  }

  const double inv_sigma_;
  const double reference_[3];
};

}  // namespace colmap_citymodel
