// Blocking worker threads shared by the CPU kernels (splat_cpu.cpp, views_cpu.cpp).
//
// Plain std::thread workers joined per call, no OpenMP: an OpenMP team spins at its barriers and
// between regions, and on a shared, oversubscribed machine that spinning doubled the CPU time per
// frame. Blocking joins cost ~50 us per call and never spin.
#pragma once

#include <algorithm>
#include <cstdint>
#include <thread>
#include <vector>

namespace image2sim_workers {

// body(worker index) on n workers: this thread is worker 0.
template <typename F>
void run_workers(int n, const F& body) {
  if (n <= 1) {
    body(0);
    return;
  }
  std::vector<std::thread> pool;
  pool.reserve(n - 1);
  for (int w = 1; w < n; ++w) pool.emplace_back([&body, w] { body(w); });
  body(0);
  for (auto& th : pool) th.join();
}

// fn(begin, end) over a static split of [0, n) into one contiguous chunk per worker, with at most
// `max_workers` workers and at least `grain` items per chunk.
template <typename F>
void parallel_range(int64_t n, int64_t grain, int64_t max_workers, const F& fn) {
  const int64_t by_grain = (n + grain - 1) / std::max<int64_t>(grain, 1);
  const int workers = static_cast<int>(std::max<int64_t>(1, std::min(max_workers, by_grain)));
  const int64_t chunk = (n + workers - 1) / workers;
  run_workers(workers, [&](int w) {
    const int64_t b = w * chunk, e = std::min<int64_t>(n, b + chunk);
    if (b < e) fn(b, e);
  });
}

}  // namespace image2sim_workers
