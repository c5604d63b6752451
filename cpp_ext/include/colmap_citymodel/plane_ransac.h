// The dominant plane of a point cloud by RANSAC: hypotheses through three
// distinct random points, each scored by its inlier count (|distance| below a
// threshold; ties by the lower inlier RMS), as many as needed to have drawn an
// all-inlier triple of the best plane so far with the given probability, at
// most `iterations`. The winner is refit by least squares to its inliers; the
// inliers returned are the winner's. What the start-up searches and the
// quality gate ask of a tie point cloud: its facades and roofs.
//
// Deterministic for a seed, whatever the number of threads: the triples are
// drawn in order from one generator, hypotheses are scored in batches in
// parallel and merged in order, and a batch's hypotheses past the stopping
// count are ignored as a sequential run would never have drawn them.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <random>
#include <stdexcept>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Eigenvalues>

#include "colmap_citymodel/parallel_for.h"

namespace colmap_citymodel {

struct PlaneFit {
  Eigen::Vector4d plane = Eigen::Vector4d::Zero();  // unit normal n and d: n.x + d = 0
  std::vector<int64_t> inliers;                     // ascending row indices
};

// Least-squares plane through `points[rows]`: the normal is the scatter
// matrix's eigenvector of the smallest eigenvalue.
inline Eigen::Vector4d FitPlane(const std::vector<Eigen::Vector3d>& points,
                                const std::vector<int64_t>& rows) {
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  for (int64_t i : rows) centre += points[i];
  centre /= static_cast<double>(rows.size());
  Eigen::Matrix3d scatter = Eigen::Matrix3d::Zero();
  for (int64_t i : rows) {
    const Eigen::Vector3d d = points[i] - centre;
    scatter += d * d.transpose();
  }
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eigen(scatter);
  const Eigen::Vector3d normal = eigen.eigenvectors().col(0).normalized();
  Eigen::Vector4d plane;
  plane << normal, -normal.dot(centre);
  return plane;
}

inline PlaneFit SegmentPlane(const double* points, int64_t n, double distance,
                             int iterations, double probability, uint64_t seed,
                             int threads = 0) {
  if (!(distance > 0.0) || !std::isfinite(distance)) {
    throw std::invalid_argument("distance must be finite and > 0");
  }
  if (iterations < 1) throw std::invalid_argument("iterations must be >= 1");
  if (!(probability > 0.0 && probability <= 1.0)) {
    throw std::invalid_argument("probability must be in (0, 1]");
  }
  PlaneFit fit;
  if (n < 3) return fit;
  for (int64_t i = 0; i < 3 * n; ++i) {
    if (!std::isfinite(points[i])) throw std::invalid_argument("points must be finite");
  }
  // Coordinates about the cloud's first point: distances keep their digits far
  // from the origin (projected coordinates).
  const Eigen::Vector3d origin(points);
  std::vector<Eigen::Vector3d> local(n);
  for (int64_t i = 0; i < n; ++i) local[i] = Eigen::Vector3d(points + 3 * i) - origin;

  std::mt19937_64 random(seed);
  std::uniform_int_distribution<int64_t> pick(0, n - 1);
  const int64_t workers = Workers(threads);
  const int64_t batch = 16 * workers;

  struct Score {
    Eigen::Vector4d plane = Eigen::Vector4d::Zero();
    int64_t count = -1;  // -1: degenerate triple
    double sum_squares = 0.0;
  };
  auto better = [](const Score& a, const Score& b) {  // a strictly better than b
    if (a.count != b.count) return a.count > b.count;
    return a.count > 0 && a.sum_squares / a.count < b.sum_squares / b.count;
  };
  auto score = [&](const Eigen::Vector4d& plane) {
    Score s;
    s.plane = plane;
    s.count = 0;
    const Eigen::Vector3d normal = plane.head<3>();
    for (int64_t i = 0; i < n; ++i) {
      const double d = std::abs(normal.dot(local[i]) + plane[3]);
      if (d < distance) {
        ++s.count;
        s.sum_squares += d * d;
      }
    }
    return s;
  };

  Score best;
  int64_t needed = iterations;
  const double log_miss_allowed = std::log(std::max(1.0 - probability, 1e-300));
  std::vector<Eigen::Vector4d> hypotheses;
  std::vector<Score> scores;
  for (int64_t drawn = 0; drawn < needed;) {
    const int64_t count = std::min<int64_t>(batch, needed - drawn);
    hypotheses.assign(count, Eigen::Vector4d::Zero());
    std::vector<bool> valid(count, false);
    for (int64_t h = 0; h < count; ++h) {
      int64_t a = pick(random), b = pick(random), c = pick(random);
      while (b == a) b = pick(random);
      while (c == a || c == b) c = pick(random);
      const Eigen::Vector3d normal = (local[b] - local[a]).cross(local[c] - local[a]);
      const double length = normal.norm();
      if (!(length > 0.0)) continue;
      hypotheses[h] << normal / length, -(normal / length).dot(local[a]);
      valid[h] = true;
    }
    scores.assign(count, Score());
    auto run = [&](int64_t from, int64_t to) {
      for (int64_t h = from; h < to; ++h) {
        if (valid[h]) scores[h] = score(hypotheses[h]);
      }
    };
    ParallelFor(count, workers, run);
    // In drawing order, as a sequential run: the stopping count may fall below
    // the hypotheses already scored in this batch.
    for (int64_t h = 0; h < count && drawn < needed; ++h, ++drawn) {
      if (scores[h].count < 0 || !better(scores[h], best)) continue;
      best = scores[h];
      const double fraction = static_cast<double>(best.count) / static_cast<double>(n);
      const double miss = 1.0 - fraction * fraction * fraction;
      if (miss <= 0.0) {
        needed = drawn + 1;
      } else if (miss < 1.0) {
        const double wanted = std::ceil(log_miss_allowed / std::log(miss));
        if (wanted < static_cast<double>(needed)) {
          needed = std::max<int64_t>(drawn + 1, static_cast<int64_t>(wanted));
        }
      }
    }
  }
  if (best.count < 3) return fit;  // every triple collinear: no plane
  const Eigen::Vector3d normal = best.plane.head<3>();
  for (int64_t i = 0; i < n; ++i) {
    if (std::abs(normal.dot(local[i]) + best.plane[3]) < distance) fit.inliers.push_back(i);
  }
  fit.plane = FitPlane(local, fit.inliers);
  fit.plane[3] -= fit.plane.head<3>().dot(origin);  // back to the caller's coordinates
  return fit;
}

}  // namespace colmap_citymodel
