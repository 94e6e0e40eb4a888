// Work on several threads: the one thread pool pattern of the library (closed orbits, bunches,
// synth's phase scans, optimizer evaluations), so each does not write its own.
#pragma once

#include <cstddef>
#include <functional>

namespace turnfit {

/// The thread count a `--threads N` asks for: N, or every hardware thread for 0 (at least 1).
unsigned resolve_thread_count(unsigned requested);

/// Runs work(worker) on `threads` workers (worker = 0 .. threads-1; worker 0 on the calling
/// thread, so threads = 1 starts no thread) and returns when all are done. If any worker
/// throws, the first exception is rethrown after every worker has finished.
void run_workers(unsigned threads, const std::function<void(unsigned worker)>& work);

/// Calls fn(i, worker) once for every i in [0, n), on min(threads, n) workers that each take
/// the next index from a shared counter (a slow item holds up only its own worker). Results
/// must go by index, so the outcome does not depend on the thread count. The first exception
/// thrown stops the handing out of indices and is rethrown when all workers are done.
void parallel_for(size_t n, unsigned threads, const std::function<void(size_t i, unsigned worker)>& fn);

}  // namespace turnfit
