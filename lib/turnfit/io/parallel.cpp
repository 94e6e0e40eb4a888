// Work on several threads (see parallel.hpp).
#include "turnfit/io/parallel.hpp"

#include <algorithm>
#include <atomic>
#include <exception>
#include <mutex>
#include <thread>
#include <vector>

namespace turnfit {

unsigned resolve_thread_count(unsigned requested) {
  if (requested > 0) return requested;
  return std::max(1u, std::thread::hardware_concurrency());
}

void run_workers(unsigned threads, const std::function<void(unsigned worker)>& work) {
  threads = std::max(1u, threads);
  std::mutex mu;
  std::exception_ptr first;
  auto guarded = [&](unsigned w) {
    try {
      work(w);
    } catch (...) {
      std::lock_guard<std::mutex> lock(mu);
      if (!first) first = std::current_exception();
    }
  };
  std::vector<std::thread> pool;
  pool.reserve(threads - 1);
  try {
    for (unsigned w = 1; w < threads; ++w) pool.emplace_back(guarded, w);
  } catch (...) {
    // Could not start a thread (resource limits): let the started ones finish, then report it
    // (a job split by worker index would otherwise lose the missing workers' part).
    for (auto& t : pool) t.join();
    throw;
  }
  guarded(0);
  for (auto& t : pool) t.join();
  if (first) std::rethrow_exception(first);
}

void parallel_for(size_t n, unsigned threads, const std::function<void(size_t i, unsigned worker)>& fn) {
  if (n == 0) return;
  std::atomic<size_t> next{0};
  std::atomic<bool> failed{false};
  const unsigned workers = static_cast<unsigned>(std::min<size_t>(std::max(1u, threads), n));
  run_workers(workers, [&](unsigned w) {
    for (size_t i; !failed.load(std::memory_order_relaxed) && (i = next.fetch_add(1)) < n;) {
      try {
        fn(i, w);
      } catch (...) {
        failed = true;
        throw;
      }
    }
  });
}

}  // namespace turnfit
