// Linear conditions on several 3D points, observed as zero:
//
//   residual = A (X - X_0),   X = [X_1; ...; X_K] stacked (3K), A (m x 3K)
//
// Model correction holds the corrected model's datum with it: the similarity
// (shift, rotation, scale) that best explains the corrected vertices' moves
// along their planes' normals is observed as zero, so that the images change
// the model's shape and leave its georeference to the model as given
// (colmap_citymodel/adjust/model_correction.py builds A). Linear, so the
// Jacobian of block k is the constant A[:, 3k:3k+3].
//
// Parameter blocks: X_1 ... X_K (3 each).
#pragma once

#include <Eigen/Core>
#include <ceres/ceres.h>

#include <vector>

namespace colmap_citymodel {

class LinearPointsConditionCost : public ceres::CostFunction {
 public:
  LinearPointsConditionCost(const Eigen::MatrixXd& matrix,
                            const Eigen::VectorXd& reference)
      : matrix_(matrix), reference_(reference) {
    set_num_residuals(static_cast<int>(matrix_.rows()));
    const int num_points = static_cast<int>(matrix_.cols() / 3);
    std::vector<int32_t>* sizes = mutable_parameter_block_sizes();
    sizes->assign(num_points, 3);
  }

  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    const int num_points = static_cast<int>(matrix_.cols() / 3);
    Eigen::Map<Eigen::VectorXd> r(residuals, matrix_.rows());
    r.setZero();
    for (int k = 0; k < num_points; ++k) {
      const Eigen::Map<const Eigen::Vector3d> point(parameters[k]);
      r.noalias() += matrix_.middleCols<3>(3 * k) *
                     (point - reference_.segment<3>(3 * k));
    }
    if (jacobians != nullptr) {
      for (int k = 0; k < num_points; ++k) {
        if (jacobians[k] == nullptr) continue;
        Eigen::Map<Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>>
            jacobian(jacobians[k], matrix_.rows(), 3);
        jacobian = matrix_.middleCols<3>(3 * k);
      }
    }
    return true;
  }

  static ceres::CostFunction* Create(const Eigen::MatrixXd& matrix,
                                     const Eigen::VectorXd& reference) {
    return new LinearPointsConditionCost(matrix, reference);
  }

 private:
  const Eigen::MatrixXd matrix_;
  const Eigen::VectorXd reference_;
};

}  // namespace colmap_citymodel
