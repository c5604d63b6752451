// Unsigned distance from points to a triangle mesh, up to a reach: what the
// start-up searches and the quality gate ask of the city model ("how many tie
// points lie within r of a surface?"). Each triangle is listed in the cells of
// a regular grid that its bounding box, grown by the reach, overlaps; a point
// then only visits the triangles listed in its own cell. Every triangle closer
// than the reach is among them, so the result is exact below the reach.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <stdexcept>
#include <vector>

#include <Eigen/Core>

#include "colmap_citymodel/parallel_for.h"

namespace colmap_citymodel {

// The point of triangle (a, b, c) closest to p (Ericson, Real-Time Collision
// Detection, 5.1.5): by the Voronoi region of p among vertices, edges, face.
inline Eigen::Vector3d ClosestPointOnTriangle(const Eigen::Vector3d& p,
                                              const Eigen::Vector3d& a,
                                              const Eigen::Vector3d& b,
                                              const Eigen::Vector3d& c) {
  const Eigen::Vector3d ab = b - a, ac = c - a, ap = p - a;
  const double d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0.0 && d2 <= 0.0) return a;
  const Eigen::Vector3d bp = p - b;
  const double d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0.0 && d4 <= d3) return b;
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) return a + (d1 / (d1 - d3)) * ab;
  const Eigen::Vector3d cp = p - c;
  const double d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0.0 && d5 <= d6) return c;
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) return a + (d2 / (d2 - d6)) * ac;
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0) {
    return b + ((d4 - d3) / ((d4 - d3) + (d5 - d6))) * (c - b);
  }
  const double denominator = va + vb + vc;
  if (!(denominator > 0.0)) {  // degenerate (zero-area) triangle: nearest vertex
    const double da = ap.squaredNorm(), db = bp.squaredNorm(), dc = cp.squaredNorm();
    return da <= db && da <= dc ? a : (db <= dc ? b : c);
  }
  return a + ab * (vb / denominator) + ac * (vc / denominator);
}

class TriangleDistance {
 public:
  using Points = Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>;
  using Triangles = Eigen::Matrix<int64_t, Eigen::Dynamic, 3, Eigen::RowMajor>;

  // `max_cells` bounds the grid's memory: a larger model gets larger cells
  // (more triangles per cell, same results).
  TriangleDistance(const Points& vertices, const Triangles& triangles,
                   double reach, int64_t max_cells = 2'000'000)
      : reach_(reach) {
    if (!(reach > 0.0) || !std::isfinite(reach)) {
      throw std::invalid_argument("reach must be finite and > 0");
    }
    const int64_t num_vertices = vertices.rows();
    for (int64_t t = 0; t < triangles.rows(); ++t) {
      for (int k = 0; k < 3; ++k) {
        if (triangles(t, k) < 0 || triangles(t, k) >= num_vertices) {
          throw std::invalid_argument("triangle vertex index out of range");
        }
      }
      corners_.push_back(vertices.row(triangles(t, 0)).transpose());
      corners_.push_back(vertices.row(triangles(t, 1)).transpose());
      corners_.push_back(vertices.row(triangles(t, 2)).transpose());
    }
    if (!vertices.allFinite()) {
      throw std::invalid_argument("vertices must be finite");
    }
    const int64_t num_triangles = triangles.rows();
    if (num_triangles == 0) return;
    Eigen::Vector3d lower = corners_[0], upper = corners_[0];
    for (const auto& corner : corners_) {
      lower = lower.cwiseMin(corner);
      upper = upper.cwiseMax(corner);
    }
    lower_ = (lower.array() - reach).matrix();
    const Eigen::Vector3d extent = ((upper.array() + reach) - lower_.array()).matrix();
    cell_ = reach;
    const double cells = (extent / cell_).array().ceil().prod();
    if (cells > static_cast<double>(max_cells)) {
      cell_ *= std::cbrt(cells / static_cast<double>(max_cells));
    }
    for (int k = 0; k < 3; ++k) {
      shape_[k] = std::max<int64_t>(1, static_cast<int64_t>(std::ceil(extent[k] / cell_)));
    }
    // Two passes over the triangles' cell ranges: count, then fill (CSR).
    std::vector<int64_t> count(shape_[0] * shape_[1] * shape_[2] + 1, 0);
    auto visit = [&](int64_t t, auto&& action) {
      const Eigen::Vector3d& a = corners_[3 * t];
      const Eigen::Vector3d& b = corners_[3 * t + 1];
      const Eigen::Vector3d& c = corners_[3 * t + 2];
      const Eigen::Vector3d low = (a.cwiseMin(b).cwiseMin(c).array() - reach).matrix();
      const Eigen::Vector3d high = (a.cwiseMax(b).cwiseMax(c).array() + reach).matrix();
      int64_t from[3], to[3];
      for (int k = 0; k < 3; ++k) {
        from[k] = Clamp(static_cast<int64_t>(std::floor((low[k] - lower_[k]) / cell_)), k);
        to[k] = Clamp(static_cast<int64_t>(std::floor((high[k] - lower_[k]) / cell_)), k);
      }
      for (int64_t i = from[0]; i <= to[0]; ++i)
        for (int64_t j = from[1]; j <= to[1]; ++j)
          for (int64_t l = from[2]; l <= to[2]; ++l) action(Index(i, j, l));
    };
    for (int64_t t = 0; t < num_triangles; ++t) {
      visit(t, [&](int64_t cell) { ++count[cell + 1]; });
    }
    for (size_t k = 1; k < count.size(); ++k) count[k] += count[k - 1];
    start_ = count;
    triangles_.resize(count.back());
    for (int64_t t = 0; t < num_triangles; ++t) {
      visit(t, [&](int64_t cell) { triangles_[count[cell]++] = static_cast<int32_t>(t); });
    }
  }

  double reach() const { return reach_; }

  // Distance from p to the nearest triangle, or the reach where none is closer.
  double operator()(const Eigen::Vector3d& p) const {
    if (start_.empty()) return reach_;
    int64_t index[3];
    for (int k = 0; k < 3; ++k) {
      const double u = std::floor((p[k] - lower_[k]) / cell_);
      if (!(u >= 0.0) || u >= static_cast<double>(shape_[k])) return reach_;
      index[k] = static_cast<int64_t>(u);
    }
    const int64_t cell = Index(index[0], index[1], index[2]);
    double best = reach_ * reach_;
    for (int64_t n = start_[cell]; n < start_[cell + 1]; ++n) {
      const int64_t t = triangles_[n];
      const double d = (ClosestPointOnTriangle(p, corners_[3 * t], corners_[3 * t + 1],
                                               corners_[3 * t + 2]) - p).squaredNorm();
      best = std::min(best, d);
    }
    return std::sqrt(best);
  }

  // Distances of n points (row-major n x 3) into `out`, on up to `threads`
  // threads (0: all cores).
  void Distances(const double* points, int64_t n, double* out, int threads = 0) const {
    // At least 20,000 points a thread: below that, starting threads costs more.
    const int64_t workers = std::min(Workers(threads), std::max<int64_t>(n / 20000, 1));
    auto run = [&](int64_t from, int64_t to) {
      for (int64_t i = from; i < to; ++i) {
        out[i] = (*this)(Eigen::Vector3d(points[3 * i], points[3 * i + 1], points[3 * i + 2]));
      }
    };
    ParallelFor(n, workers, run);
  }

 private:
  int64_t Clamp(int64_t value, int axis) const {
    return std::clamp<int64_t>(value, 0, shape_[axis] - 1);
  }
  int64_t Index(int64_t i, int64_t j, int64_t l) const {
    return (i * shape_[1] + j) * shape_[2] + l;
  }

  double reach_;
  double cell_ = 1.0;
  Eigen::Vector3d lower_ = Eigen::Vector3d::Zero();
  int64_t shape_[3] = {1, 1, 1};
  std::vector<Eigen::Vector3d> corners_;  // a, b, c of each triangle
  std::vector<int64_t> start_;            // CSR: the triangles of each cell
  std::vector<int32_t> triangles_;
};

}  // namespace colmap_citymodel
