// A robust loss that the owner of a problem switches on and off between solves:
// Huber's loss at a scale while its switch is on, none while it is off. The
// f_dTP of one problem all share one switch, so that the same problem serves
// both the robust solve of an iteration and the solve with the original
// weights: only their weights change, the problem is not built again.
//
// Switched off, the loss returns rho = (s, 1, 0), for which Ceres scales the
// residuals and Jacobians by sqrt(rho') = 1: the solve is the one without a
// loss, number for number.
#pragma once

#include <atomic>
#include <memory>

#include <ceres/loss_function.h>

namespace colmap_citymodel {

// Whether the losses that share it are robust; read by Ceres' threads during a
// solve, set between solves.
class RobustSwitch {
 public:
  explicit RobustSwitch(bool on = false) : on_(on) {}
  bool on() const { return on_.load(std::memory_order_relaxed); }
  void set(bool on) { on_.store(on, std::memory_order_relaxed); }

 private:
  std::atomic<bool> on_;
};

class SwitchableHuberLoss final : public ceres::LossFunction {
 public:
  SwitchableHuberLoss(double scale, std::shared_ptr<const RobustSwitch> robust)
      : huber_(scale), robust_(std::move(robust)) {}

  void Evaluate(double squared_norm, double rho[3]) const override {
    if (robust_->on()) {
      huber_.Evaluate(squared_norm, rho);
      return;
    }
    rho[0] = squared_norm;
    rho[1] = 1.0;
    rho[2] = 0.0;
  }

 private:
  ceres::HuberLoss huber_;
  std::shared_ptr<const RobustSwitch> robust_;
};

}  // namespace colmap_citymodel
