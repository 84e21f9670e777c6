// A fixed pool of worker threads for the cpu backend's data-parallel loops.
//
// One pool per engine, created once: per-frame thread creation would cost more than small frames
// take. ParallelFor hands out chunks dynamically (an atomic cursor), because per-tile blend cost
// varies by orders of magnitude across a street image (sky vs. parked cars).
#pragma once

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

namespace streetsim {

class ThreadPool {
 public:
  // num_threads <= 0: STREETSIM_THREADS if set, else std::thread::hardware_concurrency().
  explicit ThreadPool(int num_threads = 0);
  ~ThreadPool();
  ThreadPool(const ThreadPool&) = delete;
  ThreadPool& operator=(const ThreadPool&) = delete;

  int num_threads() const { return static_cast<int>(workers_.size()) + 1; }

  // Calls fn(begin, end, thread_index) over [0, n) in chunks of `grain`, on all threads (the
  // caller's included). thread_index < num_threads(); each index is used by one thread at a time,
  // so callers may keep per-thread scratch indexed by it. Not reentrant.
  void ParallelFor(int64_t n, int64_t grain,
                   const std::function<void(int64_t, int64_t, int)>& fn);

 private:
  void WorkerLoop(int index);
  void RunJob(int index);

  std::vector<std::thread> workers_;
  std::mutex mu_;
  std::condition_variable cv_start_;
  std::condition_variable cv_done_;
  uint64_t generation_ = 0;
  int pending_ = 0;
  bool stop_ = false;

  // The job in flight.
  const std::function<void(int64_t, int64_t, int)>* fn_ = nullptr;
  int64_t n_ = 0;
  int64_t grain_ = 1;
  std::atomic<int64_t> cursor_{0};
};

}  // namespace streetsim
