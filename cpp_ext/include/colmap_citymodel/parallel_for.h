// run(from, to) over [0, n) split into one contiguous range per worker thread
// (on the calling thread alone when one worker is asked for): the loops of
// the distance and RANSAC helpers, whose items are independent. Workers()
// turns a caller's thread count (0 or less: every core) into a count >= 1.
#pragma once

#include <algorithm>
#include <cstdint>
#include <thread>
#include <vector>

namespace colmap_citymodel {

inline int64_t Workers(int threads) {
  const int64_t cores = static_cast<int64_t>(std::thread::hardware_concurrency());
  return std::max<int64_t>(1, threads > 0 ? threads : cores);
}

template <typename Run>
void ParallelFor(int64_t n, int64_t workers, const Run& run) {
  workers = std::clamp<int64_t>(workers, 1, std::max<int64_t>(n, 1));
  if (workers == 1) {
    run(int64_t{0}, n);
    return;
  }
  std::vector<std::thread> pool;
  const int64_t chunk = (n + workers - 1) / workers;
  for (int64_t w = 0; w < workers; ++w) {
    const int64_t from = w * chunk, to = std::min(n, from + chunk);
    if (from < to) pool.emplace_back(run, from, to);
  }
  for (auto& thread : pool) thread.join();
}

}  // namespace colmap_citymodel
