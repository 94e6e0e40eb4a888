// Master/worker evaluation over MPI (only with TURNFIT_WITH_MPI), and the exact wire format of
// an evaluation (raw doubles: NaN and infinities survive, every bit is kept).
#include "turnfit/optimize/mpi.hpp"

#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <string>

#include "turnfit/io/error.hpp"

#ifdef TURNFIT_WITH_MPI
#include <mpi.h>
#endif

namespace turnfit {

bool launched_by_mpi() {
  for (const char* v : {"OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_RANK", "MPI_LOCALNRANKS"})
    if (std::getenv(v)) return true;
  return false;
}

namespace {

[[maybe_unused]] int launcher_size() {
  for (const char* v : {"OMPI_COMM_WORLD_SIZE", "PMI_SIZE"})
    if (const char* s = std::getenv(v)) return std::atoi(s);
  return 1;
}

template <class T>
void put(std::string& s, const T& v) {
  s.append(reinterpret_cast<const char*>(&v), sizeof v);
}
template <class T>
bool get(const std::string& s, size_t& pos, T& v) {
  if (pos + sizeof v > s.size()) return false;
  std::memcpy(&v, s.data() + pos, sizeof v);
  pos += sizeof v;
  return true;
}

}  // namespace

std::string encode_evaluation(const Evaluation& e) {
  std::string s;
  put<std::uint8_t>(s, e.ok ? 1 : 0);
  put<std::uint32_t>(s, static_cast<std::uint32_t>(e.f.size()));
  put<std::uint32_t>(s, static_cast<std::uint32_t>(e.g.size()));
  for (double v : e.f) put(s, v);
  for (double v : e.g) put(s, v);
  s += e.reason;
  return s;
}

Evaluation decode_evaluation(const std::string& s) {
  Evaluation e;
  size_t pos = 0;
  std::uint8_t ok = 0;
  std::uint32_t nf = 0, ng = 0;
  if (!get(s, pos, ok) || !get(s, pos, nf) || !get(s, pos, ng) || s.size() < pos + 8ull * (nf + ng)) {
    e.ok = false;
    e.reason = "malformed result from an MPI worker";
    return e;
  }
  e.ok = ok != 0;
  e.f.resize(nf);
  e.g.resize(ng);
  for (auto& v : e.f) get(s, pos, v);
  for (auto& v : e.g) get(s, pos, v);
  e.reason = s.substr(pos);
  return e;
}

#ifdef TURNFIT_WITH_MPI

namespace {
constexpr int kTagTask = 1, kTagResult = 2, kTagStop = 3;
}

MpiSession::MpiSession() {
  if (!launched_by_mpi()) return;
  int provided = 0;
  MPI_Init_thread(nullptr, nullptr, MPI_THREAD_FUNNELED, &provided);
  initialized_ = true;
  MPI_Comm_rank(MPI_COMM_WORLD, &rank_);
  MPI_Comm_size(MPI_COMM_WORLD, &size_);
}

MpiSession::~MpiSession() {
  if (initialized_) MPI_Finalize();
}

MpiEvaluator::MpiEvaluator(const MpiSession& session) : session_(session) {}

void MpiEvaluator::evaluate(const std::vector<std::vector<double>>& batch, const EvaluationSink& done) {
  const int workers = session_.size() - 1;
  size_t next = 0, busy = 0;
  std::vector<double> buf;
  auto send = [&](int worker) {
    const std::vector<double>& x = batch[next];
    buf.assign(1, static_cast<double>(next));  // the index travels as an exact double (< 2^53)
    buf.insert(buf.end(), x.begin(), x.end());
    MPI_Send(buf.data(), static_cast<int>(buf.size()), MPI_DOUBLE, worker, kTagTask, MPI_COMM_WORLD);
    ++next;
    ++busy;
  };
  for (int w = 1; w <= workers && next < batch.size(); ++w) send(w);
  std::string msg;
  while (busy > 0) {
    MPI_Status st;
    MPI_Probe(MPI_ANY_SOURCE, kTagResult, MPI_COMM_WORLD, &st);
    int n = 0;
    MPI_Get_count(&st, MPI_CHAR, &n);
    msg.assign(static_cast<size_t>(n), '\0');
    MPI_Recv(msg.data(), n, MPI_CHAR, st.MPI_SOURCE, kTagResult, MPI_COMM_WORLD, MPI_STATUS_IGNORE);
    --busy;
    std::uint64_t index = 0;
    std::memcpy(&index, msg.data(), sizeof index);
    const int worker = st.MPI_SOURCE;
    if (next < batch.size()) send(worker);
    done(static_cast<size_t>(index), decode_evaluation(msg.substr(sizeof index)));
  }
}

void MpiEvaluator::stop_workers() {
  if (stopped_) return;
  stopped_ = true;
  for (int w = 1; w < session_.size(); ++w) MPI_Send(nullptr, 0, MPI_DOUBLE, w, kTagStop, MPI_COMM_WORLD);
}

void mpi_worker_loop(const MpiSession& session, const Problem& problem) {
  (void)session;
  std::vector<double> buf;
  for (;;) {
    MPI_Status st;
    MPI_Probe(0, MPI_ANY_TAG, MPI_COMM_WORLD, &st);
    int n = 0;
    MPI_Get_count(&st, MPI_DOUBLE, &n);
    buf.resize(static_cast<size_t>(std::max(n, 1)));
    MPI_Recv(buf.data(), n, MPI_DOUBLE, 0, st.MPI_TAG, MPI_COMM_WORLD, MPI_STATUS_IGNORE);
    if (st.MPI_TAG == kTagStop) return;
    const std::uint64_t index = static_cast<std::uint64_t>(buf[0]);
    const std::vector<double> x(buf.begin() + 1, buf.begin() + n);
    Evaluation e;
    try {
      if (x.size() != problem.n_variables()) throw std::runtime_error("wrong number of variables from the master");
      e = problem.evaluate(x);
    } catch (const std::exception& ex) {
      e = Evaluation{};
      e.ok = false;
      e.reason = std::string("exception in MPI worker: ") + ex.what();
    }
    std::string out(reinterpret_cast<const char*>(&index), sizeof index);
    out += encode_evaluation(e);
    MPI_Send(out.data(), static_cast<int>(out.size()), MPI_CHAR, 0, kTagResult, MPI_COMM_WORLD);
  }
}

#else  // no MPI in this build

MpiSession::MpiSession() {
  if (launched_by_mpi() && launcher_size() > 1)
    throw usage_error("started by mpirun with " + std::to_string(launcher_size()) +
                      " ranks, but this turnfit was built without MPI (cmake -DTURNFIT_WITH_MPI=ON)");
}
MpiSession::~MpiSession() = default;
MpiEvaluator::MpiEvaluator(const MpiSession& session) : session_(session) {}
void MpiEvaluator::evaluate(const std::vector<std::vector<double>>&, const EvaluationSink&) {
  throw Error(ExitCode::software, "MPI evaluation in a build without MPI");
}
void MpiEvaluator::stop_workers() { stopped_ = true; }
void mpi_worker_loop(const MpiSession&, const Problem&) {
  throw Error(ExitCode::software, "MPI worker in a build without MPI");
}

#endif

}  // namespace turnfit
