// Python bindings of colmap_citymodel._core: factories that return
// ceres::CostFunction* for pyceres.Problem.add_residual_block, and the distance
// from points to the city model's triangles (TriangleDistance), and the
// dominant plane of a point cloud by RANSAC (segment_plane).
//
// The returned pointer is converted through the ceres::CostFunction type that
// pyceres registers, so this module must share pybind11 internals with
// pyceres/pycolmap (pybind11 3.0.x, internals v11). The Python object owns the
// cost (take_ownership); pyceres wraps it in a non-owning CostFunctionWrapper
// and keeps the Python object alive as long as the pyceres.Problem object.
#include "colmap_citymodel/baseline_length_prior.h"
#include "colmap_citymodel/linear_points_condition.h"
#include "colmap_citymodel/mark_ray.h"
#include "colmap_citymodel/plane_ransac.h"
#include "colmap_citymodel/point_plane_distance.h"
#include "colmap_citymodel/point_plane_effects_distance.h"
#include "colmap_citymodel/point_plane_offset_distance.h"
#include "colmap_citymodel/point_position_prior.h"
#include "colmap_citymodel/projection_center_offset_prior.h"
#include "colmap_citymodel/projection_center_prior.h"
#include "colmap_citymodel/scalar_prior.h"
#include "colmap_citymodel/switchable_loss.h"
#include "colmap_citymodel/triangle_distance.h"

#include <stdexcept>
#include <string>

#include <ceres/version.h>
#include <pybind11/eigen.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

namespace py = pybind11;
using namespace pybind11::literals;
using namespace colmap_citymodel;

namespace {

void CheckSigma(double sigma, const char* what) {
  if (!(sigma > 0.0) || !std::isfinite(sigma)) {
    throw std::invalid_argument(std::string(what) +
                                " must be finite and > 0, got " +
                                std::to_string(sigma));
  }
}

void CheckFinite(const Eigen::Vector3d& value, const char* what) {
  if (!value.allFinite()) {
    throw std::invalid_argument(std::string(what) + " must be finite");
  }
}

Eigen::Matrix3d SqrtInformationFromSigma(const Eigen::Vector3d& sigma) {
  for (int i = 0; i < 3; ++i) CheckSigma(sigma(i), "sigma_xyz");
  return sigma.cwiseInverse().asDiagonal();
}

void CheckSqrtInformation(const Eigen::Matrix3d& sqrt_information) {
  if (!sqrt_information.allFinite() ||
      std::abs(sqrt_information.determinant()) <= 0.0) {
    throw std::invalid_argument(
        "sqrt_information must be a finite, invertible 3x3 matrix");
  }
}

}  // namespace

PYBIND11_MODULE(_core, m) {
  m.doc() =
      "Ceres cost functions of colmap-citymodel's hybrid bundle adjustment, "
      "returned as ceres::CostFunction for pyceres / pycolmap problems, the "
      "distance from points to the city model's triangles, and the dominant plane "
      "of a point cloud by RANSAC.";

  // Registers ceres::CostFunction with pybind11; without it the factories
  // below cannot convert their return value.
  py::module_::import("pyceres");

  constexpr auto kTake = py::return_value_policy::take_ownership;

  m.def(
      "PointPlaneDistanceCost",
      [](double sigma, const Eigen::Vector3d& reference) -> ceres::CostFunction* {
        CheckSigma(sigma, "sigma");
        CheckFinite(reference, "reference");
        return PointPlaneDistanceCostFunctor::Create(sigma, reference.data());
      },
      "sigma"_a,
      "reference"_a = Eigen::Vector3d::Zero(),
      kTake,
      "Point-to-plane distance, residual = (n.(X - reference)/|n| + d) / sigma.\n"
      "Parameter blocks: point (3), normal (3, use pyceres.SphereManifold(3)),"
      " offset (1) at the plane's reference point (a constant on the plane).");

  m.def(
      "PointPlaneOffsetDistanceCost",
      [](double sigma, const Eigen::Vector3d& reference) -> ceres::CostFunction* {
        CheckSigma(sigma, "sigma");
        CheckFinite(reference, "reference");
        return PointPlaneOffsetDistanceCostFunctor::Create(sigma, reference.data());
      },
      "sigma"_a,
      "reference"_a = Eigen::Vector3d::Zero(),
      kTake,
      "Point-to-plane distance with the plane's generalisation offset o,\n"
      "residual = (n.(X - reference)/|n| + d + o) / sigma.\nParameter blocks: point (3), "
      "normal (3, use pyceres.SphereManifold(3)), offset (1), generalisation "
      "offset (1).");

  m.def(
      "PointPlaneEffectsDistanceCost",
      [](double sigma, const Eigen::Vector3d& reference,
         const Eigen::Matrix<double, 2, 3>& tilt_axes, double length0,
         bool scaled) -> ceres::CostFunction* {
        CheckSigma(sigma, "sigma");
        CheckFinite(reference, "reference");
        if (!tilt_axes.allFinite()) throw std::invalid_argument("tilt_axes must be finite");
        if (scaled) CheckSigma(length0, "length0");
        return new PointPlaneEffectsDistanceCost(sigma, reference, tilt_axes, length0,
                                                 scaled);
      },
      "sigma"_a,
      "reference"_a,
      "tilt_axes"_a,
      "length0"_a,
      "scaled"_a,
      kTake,
      "Point-to-face distance with the face's generalisation error as a random effect\n"
      "e = (offset, tilt 1, tilt 2), in the block's units: residual = (n.(X - reference)/|n|\n"
      "+ d + e0 + e1 a1.(X - reference) + e2 a2.(X - reference)) / (sigma s), a_k the rows of\n"
      "tilt_axes, s = |C_a - C_b| / length0 (1 unless scaled).\nParameter blocks: point (3),\n"
      "normal (3), offset (1), effects (3), rig_from_world (7) of two frames.");

  m.def(
      "ScalarPriorCost",
      [](double observed, double sigma) -> ceres::CostFunction* {
        CheckSigma(sigma, "sigma");
        if (!std::isfinite(observed)) {
          throw std::invalid_argument("observed must be finite");
        }
        return ScalarPriorCostFunctor::Create(observed, sigma);
      },
      "observed"_a,
      "sigma"_a,
      kTake,
      "Direct observation of a scalar, residual = (x - observed) / sigma.\n"
      "Parameter block: x (1).");

  m.def(
      "PointPositionPriorCost",
      [](const Eigen::Vector3d& observed_xyz,
         const Eigen::Vector3d& sigma_xyz) -> ceres::CostFunction* {
        return PointPositionPriorCostFunctor::Create(
            observed_xyz, SqrtInformationFromSigma(sigma_xyz));
      },
      "observed_xyz"_a,
      "sigma_xyz"_a,
      kTake,
      "Direct observation of a point, residual = (X - X_obs) / sigma per "
      "axis.\nParameter block: point (3).");
  m.def(
      "PointPositionPriorCost",
      [](const Eigen::Vector3d& observed_xyz,
         const Eigen::Matrix3d& sqrt_information) -> ceres::CostFunction* {
        CheckSqrtInformation(sqrt_information);
        return PointPositionPriorCostFunctor::Create(observed_xyz,
                                                     sqrt_information);
      },
      "observed_xyz"_a,
      "sqrt_information"_a,
      kTake,
      "Direct observation of a point, residual = L (X - X_obs) with "
      "L^T L = Sigma^-1.\nParameter block: point (3).");

  m.def(
      "ProjectionCenterPriorCost",
      [](const Eigen::Vector3d& observed_xyz,
         const Eigen::Vector3d& sigma_xyz,
         const Eigen::Vector3d& position_in_rig) -> ceres::CostFunction* {
        return ProjectionCenterPriorCostFunctor::Create(
            observed_xyz, SqrtInformationFromSigma(sigma_xyz), position_in_rig);
      },
      "observed_xyz"_a,
      "sigma_xyz"_a,
      "position_in_rig"_a = Eigen::Vector3d::Zero(),
      kTake,
      "GNSS position prior on a frame, residual = (R^T (p_in_rig - t) - "
      "P_obs) / sigma per axis.\nParameter block: rig_from_world.params (7: "
      "qx, qy, qz, qw, tx, ty, tz).");
  m.def(
      "ProjectionCenterPriorCost",
      [](const Eigen::Vector3d& observed_xyz,
         const Eigen::Matrix3d& sqrt_information,
         const Eigen::Vector3d& position_in_rig) -> ceres::CostFunction* {
        CheckSqrtInformation(sqrt_information);
        return ProjectionCenterPriorCostFunctor::Create(
            observed_xyz, sqrt_information, position_in_rig);
      },
      "observed_xyz"_a,
      "sqrt_information"_a,
      "position_in_rig"_a = Eigen::Vector3d::Zero(),
      kTake,
      "GNSS position prior on a frame, residual = L (R^T (p_in_rig - t) - "
      "P_obs) with L^T L = Sigma^-1.\nParameter block: rig_from_world.params "
      "(7).");

  m.def(
      "ProjectionCenterOffsetPriorCost",
      [](const Eigen::Vector3d& observed_xyz, const Eigen::Vector3d& sigma_xyz,
         const Eigen::Vector3d& position_in_rig,
         const Eigen::MatrixXd& directions) -> ceres::CostFunction* {
        CheckFinite(observed_xyz, "observed_xyz");
        CheckFinite(position_in_rig, "position_in_rig");
        if (directions.rows() != 3 || !directions.allFinite()) {
          throw std::invalid_argument("directions must be a finite 3 x k matrix");
        }
        const Eigen::Matrix3d sqrt_information = SqrtInformationFromSigma(sigma_xyz);
        if (directions.cols() == 1) {
          return ProjectionCenterOffsetPriorCostFunctor<1>::Create(
              observed_xyz, sqrt_information, position_in_rig, directions);
        }
        if (directions.cols() == 3) {
          return ProjectionCenterOffsetPriorCostFunctor<3>::Create(
              observed_xyz, sqrt_information, position_in_rig, directions);
        }
        throw std::invalid_argument("directions must have 1 or 3 columns, got " +
                                    std::to_string(directions.cols()));
      },
      "observed_xyz"_a,
      "sigma_xyz"_a,
      "position_in_rig"_a,
      "directions"_a,
      kTake,
      "GNSS position prior with a constant offset b of the observations, "
      "residual = (R^T (p_in_rig - t) - (P_obs + D b)) / sigma per axis; D is "
      "3 x k (k = 1: a height offset along (0, 0, 1); k = 3: a 3D bias).\n"
      "Parameter blocks: rig_from_world.params (7), b (k).");

  m.def(
      "BaselineLengthPriorCost",
      [](double length, double sigma, const Eigen::Vector3d& position_in_rig_a,
         const Eigen::Vector3d& position_in_rig_b) -> ceres::CostFunction* {
        if (!(sigma > 0.0)) {
          throw std::invalid_argument("sigma must be positive");
        }
        return BaselineLengthPriorCostFunctor::Create(length, sigma, position_in_rig_a,
                                                      position_in_rig_b);
      },
      "length"_a,
      "sigma"_a,
      "position_in_rig_a"_a = Eigen::Vector3d::Zero(),
      "position_in_rig_b"_a = Eigen::Vector3d::Zero(),
      kTake,
      "Prior on the distance of two positions fixed in two rigs, residual = "
      "(|P_a - P_b| - length) / sigma with P = R^T (p_in_rig - t).\nParameter "
      "blocks: rig_from_world.params of a and of b (7 each).");

  m.def(
      "MarkRayCost",
      [](const Eigen::Vector2d& normalised, double focal, double sigma,
         const Eigen::Vector4d& cam_from_rig_xyzw,
         const Eigen::Vector3d& cam_from_rig_translation) -> ceres::CostFunction* {
        CheckSigma(sigma, "sigma");
        CheckSigma(focal, "focal");
        if (!normalised.allFinite()) {
          throw std::invalid_argument("normalised must be finite");
        }
        CheckFinite(cam_from_rig_translation, "cam_from_rig_translation");
        Eigen::Quaterniond rotation(cam_from_rig_xyzw(3), cam_from_rig_xyzw(0),
                                    cam_from_rig_xyzw(1), cam_from_rig_xyzw(2));
        if (!(rotation.norm() > 0.0) || !cam_from_rig_xyzw.allFinite()) {
          throw std::invalid_argument("cam_from_rig_xyzw must be a finite quaternion");
        }
        rotation.normalize();
        return MarkRayCostFunctor::Create(normalised, focal / sigma, rotation,
                                          cam_from_rig_translation);
      },
      "normalised"_a,
      "focal"_a,
      "sigma"_a,
      "cam_from_rig_xyzw"_a = Eigen::Vector4d(0.0, 0.0, 0.0, 1.0),
      "cam_from_rig_translation"_a = Eigen::Vector3d::Zero(),
      kTake,
      "A ground mark measured in an image: residual = (focal / sigma) "
      "(X_cam.xy / X_cam.z - normalised), X_cam = cam_from_rig (rig_from_world "
      "X), normalised the measured pixel in the normalised image plane.\n"
      "Parameter blocks: X (3), rig_from_world.params (7).");

  m.def(
      "LinearPointsConditionCost",
      [](const Eigen::MatrixXd& matrix,
         const Eigen::VectorXd& reference) -> ceres::CostFunction* {
        if (matrix.rows() < 1 || matrix.cols() < 3 || matrix.cols() % 3 != 0) {
          throw std::invalid_argument(
              "matrix must have at least one row and 3K columns (K >= 1)");
        }
        if (reference.size() != matrix.cols()) {
          throw std::invalid_argument("reference must have 3K values, one per column");
        }
        if (!matrix.allFinite() || !reference.allFinite()) {
          throw std::invalid_argument("matrix and reference must be finite");
        }
        return LinearPointsConditionCost::Create(matrix, reference);
      },
      "matrix"_a,
      "reference"_a,
      kTake,
      "Linear conditions on K points observed as zero, residual = A (X - X_0) "
      "with X the stacked points.\nParameter blocks: K points (3 each).");

  py::class_<TriangleDistance>(
      m, "TriangleDistance",
      "Unsigned distance from points to a triangle mesh up to `reach` (m): exact "
      "below it, `reach` where no triangle is closer.")
      .def(py::init<const TriangleDistance::Points&, const TriangleDistance::Triangles&,
                    double, int64_t>(),
           "vertices"_a, "triangles"_a, "reach"_a, "max_cells"_a = 2'000'000,
           "vertices (V, 3) float64, triangles (T, 3) vertex indices; a model larger "
           "than max_cells cells of the reach's size gets larger cells.")
      .def_property_readonly("reach", &TriangleDistance::reach)
      .def(
          "__call__",
          [](const TriangleDistance& self,
             const py::array_t<double, py::array::c_style | py::array::forcecast>& points,
             int threads) {
            if (points.ndim() != 2 || points.shape(1) != 3) {
              throw std::invalid_argument("points must have shape (N, 3)");
            }
            const int64_t n = points.shape(0);
            py::array_t<double> out(n);
            const double* in = points.data();
            double* result = out.mutable_data();
            {
              py::gil_scoped_release release;
              self.Distances(in, n, result, threads);
            }
            return out;
          },
          "points"_a, "threads"_a = 0,
          "Distances (N,) of points (N, 3); threads 0: all cores.");

  m.def(
      "segment_plane",
      [](const py::array_t<double, py::array::c_style | py::array::forcecast>& points,
         double distance, int iterations, double probability, uint64_t seed, int threads) {
        if (points.ndim() != 2 || points.shape(1) != 3) {
          throw std::invalid_argument("points must have shape (N, 3)");
        }
        PlaneFit fit;
        {
          py::gil_scoped_release release;
          fit = SegmentPlane(points.data(), points.shape(0), distance, iterations,
                             probability, seed, threads);
        }
        py::array_t<double> plane(4);
        std::copy(fit.plane.data(), fit.plane.data() + 4, plane.mutable_data());
        py::array_t<int64_t> inliers(static_cast<py::ssize_t>(fit.inliers.size()));
        std::copy(fit.inliers.begin(), fit.inliers.end(), inliers.mutable_data());
        return py::make_tuple(plane, inliers);
      },
      "points"_a, "distance"_a, "iterations"_a = 500, "probability"_a = 0.99999999,
      "seed"_a = 0, "threads"_a = 0,
      "The dominant plane of points (N, 3) by RANSAC: (plane (4,) with unit normal n and "
      "d, n.x + d = 0, refit to its inliers; inlier row indices (K,) ascending), inliers "
      "closer than `distance`. No plane (fewer than 3 points, all collinear): zeros and "
      "no inliers. The same for a seed on any number of threads (0: all cores).");

  py::class_<RobustSwitch, std::shared_ptr<RobustSwitch>>(
      m, "RobustSwitch",
      "Whether the SwitchableHuberLoss objects that share this switch are robust (set it "
      "between solves, never during one).")
      .def(py::init<bool>(), "on"_a = false)
      .def_property("on", &RobustSwitch::on, &RobustSwitch::set);

  m.def(
      "SwitchableHuberLoss",
      [](double scale, std::shared_ptr<RobustSwitch> robust)
          -> std::shared_ptr<ceres::LossFunction> {
        CheckSigma(scale, "scale");
        if (!robust) throw std::invalid_argument("robust must be a RobustSwitch");
        return std::make_shared<SwitchableHuberLoss>(scale, std::move(robust));
      },
      "scale"_a, "robust"_a,
      "A loss for pyceres.Problem.add_residual_block: Huber's at `scale` while `robust.on`, "
      "none (rho = s) while it is off.");

  m.attr("__ceres_version__") = CERES_VERSION_STRING;
  m.attr("__pybind11_version__") = COLMAP_CITYMODEL_PYBIND11_VERSION;
  m.attr("__pybind11_internals_version__") = PYBIND11_INTERNALS_VERSION;
#ifdef PYBIND11_INTERNALS_ID
  m.attr("__pybind11_internals_id__") = PYBIND11_INTERNALS_ID;
#endif
}
