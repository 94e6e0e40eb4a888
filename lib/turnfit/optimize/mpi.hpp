// MPI scale-out for turnfit-nsga: one master runs the engine, the other ranks evaluate designs
// as they are handed out (dynamic scheduling). Builds without MPI keep the same interface.
#pragma once

#include <vector>

#include "turnfit/optimize/nsga2.hpp"

namespace turnfit {

/// Whether this process was started by an MPI launcher (mpirun/mpiexec set their variables).
bool launched_by_mpi();

/// MPI for the life of the object: initialized only when launched_by_mpi() (so the same binary
/// runs alone without an MPI runtime), finalized at the end. In a build without MPI, a launch
/// by mpirun with more than one rank is an EX_USAGE error on every rank (else each rank would
/// run the whole optimization and write the same files).
class MpiSession {
 public:
  /// Initializes MPI when launched by mpirun.
  MpiSession();
  ~MpiSession();
  MpiSession(const MpiSession&) = delete;
  MpiSession& operator=(const MpiSession&) = delete;
  /// This process's rank (0 alone).
  int rank() const { return rank_; }
  /// Number of ranks (1 alone).
  int size() const { return size_; }

 private:
  bool initialized_ = false;
  int rank_ = 0, size_ = 1;
};

/// The master's side: hands designs to the workers (ranks 1 .. size-1) one at a time, the next
/// to whichever answers first, so a slow design holds up only its worker.
class MpiEvaluator : public Evaluator {
 public:
  /// An evaluator over the session's workers (size() >= 2).
  explicit MpiEvaluator(const MpiSession& session);
  /// Evaluates the batch on the workers; returns when all are done.
  void evaluate(const std::vector<std::vector<double>>& batch, const EvaluationSink& done) override;
  /// Tells every worker to leave mpi_worker_loop (call once, also after an error).
  void stop_workers();

 private:
  const MpiSession& session_;
  bool stopped_ = false;
};

/// A worker's life: receives designs, evaluates them with problem.evaluate (an exception
/// becomes a failed evaluation), sends the results back, until the master says stop.
void mpi_worker_loop(const MpiSession& session, const Problem& problem);

/// Encodes an evaluation exactly (doubles round-trip) for the wire; and back.
std::string encode_evaluation(const Evaluation& e);
/// Decodes encode_evaluation's text (a malformed text gives a failed evaluation).
Evaluation decode_evaluation(const std::string& text);

}  // namespace turnfit
