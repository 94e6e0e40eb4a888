// Bunch generation (Gaussian in Twiss form, or a file of offsets) and multi-threaded tracking
// reduced to centroids and probe histograms, independent of the thread count.
#include "turnfit/track/bunch.hpp"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <exception>
#include <functional>

#include <Eigen/Dense>

#include "turnfit/io/csv.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/io/parallel.hpp"
#include "turnfit/physics/particle.hpp"
#include "turnfit/track/integrators.hpp"

namespace turnfit {
namespace {

/// SplitMix64 (Steele, Lea, Flood 2014): a small generator whose every output is a
/// bijective mix of a counter, so seeding one stream per particle gives independent streams.
struct SplitMix {
  std::uint64_t s;
  std::uint64_t next() {
    std::uint64_t z = (s += 0x9e3779b97f4a7c15ULL);
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
    return z ^ (z >> 31);
  }
  /// Uniform in (0, 1): 53 random bits, never 0 (log in Box-Muller).
  double uniform() { return (static_cast<double>(next() >> 11) + 0.5) * 0x1.0p-53; }
};

/// Standard normal variates by Box-Muller (our own, so particles are the same with every
/// standard library), each redrawn until |u| <= cutoff (cutoff 0: untruncated).
class Normal {
 public:
  Normal(std::uint64_t seed, std::uint64_t index) {
    SplitMix mix{seed};
    rng_.s = mix.next() ^ (index * 0xd1b54a32d192ed03ULL);
    rng_.next();  // decorrelate neighbouring indices
  }
  double draw(double cutoff) {
    for (;;) {
      double u = next();
      if (!(cutoff > 0) || std::fabs(u) <= cutoff) return u;
    }
  }

 private:
  double next() {
    if (have_) {
      have_ = false;
      return spare_;
    }
    const double a = std::sqrt(-2 * std::log(rng_.uniform())), b = 2 * kPi * rng_.uniform();
    spare_ = a * std::sin(b);
    have_ = true;
    return a * std::cos(b);
  }
  SplitMix rng_{0};
  double spare_ = 0;
  bool have_ = false;
};

/// Sums over the particles of one (probe, turn) crossing.
struct Acc {
  std::uint64_t n = 0;
  double r = 0, m2 = 0;  // mean radius and sum of squared deviations (Welford): r^2 sums would
                         // lose the micrometre spread of a 4 m radius to cancellation
  double s = 0, t = 0, e = 0, pc = 0, ps = 0;
  bool phase = true;
  void add(const TurnRecord& tr) {
    ++n;
    const double d = tr.r_mm - r;
    r += d / static_cast<double>(n);
    m2 += d * (tr.r_mm - r);
    s += tr.s_mm;
    t += tr.t_ns;
    e += tr.energy_MeV;
    if (std::isfinite(tr.phase_deg)) {
      pc += std::cos(tr.phase_deg * kPi / 180);
      ps += std::sin(tr.phase_deg * kPi / 180);
    } else {
      phase = false;
    }
  }
  void merge(const Acc& o) {
    if (o.n == 0) return;
    // Chan, Golub, LeVeque (1979): pairwise combination of means and squared deviations.
    const double na = static_cast<double>(n), nb = static_cast<double>(o.n), d = o.r - r;
    n += o.n;
    r += d * nb / (na + nb);
    m2 += o.m2 + d * d * na * nb / (na + nb);
    s += o.s;
    t += o.t;
    e += o.e;
    pc += o.pc;
    ps += o.ps;
    phase = phase && o.phase;
  }
};

/// What a chunk of particles contributes to the sums; merged in chunk order, since floating
/// point sums depend on their order. (Histogram counts are integers: each worker thread keeps
/// one set, which keeps memory independent of the bunch size.)
struct Partial {
  std::vector<std::vector<Acc>> acc;  // [probe][turn - 1]
  std::vector<std::pair<size_t, TrackEnd>> lost;
  double turns = 0;
};

constexpr size_t kChunk = 16;  // particles per reduction chunk (fixed: results must not
                               // depend on how chunks are spread over threads)

void merge_into(Partial& dst, Partial& src) {
  if (dst.acc.size() < src.acc.size()) dst.acc.resize(src.acc.size());
  for (size_t p = 0; p < src.acc.size(); ++p) {
    if (dst.acc[p].size() < src.acc[p].size()) dst.acc[p].resize(src.acc[p].size());
    for (size_t k = 0; k < src.acc[p].size(); ++k) dst.acc[p][k].merge(src.acc[p][k]);
  }
  for (auto& l : src.lost) dst.lost.push_back(std::move(l));
  dst.turns += src.turns;
}

}  // namespace

BunchOffset& operator+=(BunchOffset& a, const BunchOffset& b) {
  a.dr_mm += b.dr_mm;
  a.dpr_mrad += b.dpr_mrad;
  a.dz_mm += b.dz_mm;
  a.dpz_mrad += b.dpz_mrad;
  a.dE_MeV += b.dE_MeV;
  a.dphase_deg += b.dphase_deg;
  return a;
}

BunchOffset scaled(const BunchOffset& d, double f) {
  return {f * d.dr_mm, f * d.dpr_mrad, f * d.dz_mm, f * d.dpz_mrad, f * d.dE_MeV, f * d.dphase_deg};
}

std::vector<ProbeHistogram> empty_histograms(const TrackModel& m) {
  std::vector<ProbeHistogram> h(m.probes.size());
  for (size_t p = 0; p < m.probes.size(); ++p) {
    // Bins on the recorded radius (turns.csv's r_mm: true radius minus the shift) over the
    // radii the probe spans; for an offset probe these differ from s by a^2 / (2 s).
    const ProbeLine& pl = m.probes[p];
    // The probe's ends sit at s + shift along its line; their recorded radii are what the
    // crossings there record (ProbeLine::recorded_r, which also handles a hidden probe-offset).
    auto recorded_r = [&](double s) {
      const double at = s + pl.shift_m;
      return pl.recorded_r(std::hypot(at, pl.a_m), at) * 1e3;
    };
    h[p].lo_mm = recorded_r(pl.s_min_m);
    h[p].step_mm = pl.step_m * 1e3;
    const double span = recorded_r(pl.s_max_m) - h[p].lo_mm;
    h[p].counts.assign(static_cast<size_t>(std::max(1.0, std::ceil(span / h[p].step_mm - 1e-9))), 0);
  }
  return h;
}

void add_crossing(std::vector<ProbeHistogram>& hist, const TurnRecord& tr) {
  ProbeHistogram& h = hist[static_cast<size_t>(tr.probe)];
  const double k = std::floor((tr.r_mm - h.lo_mm) / h.step_mm);
  if (k >= 0 && k < static_cast<double>(h.counts.size())) ++h.counts[static_cast<size_t>(k)];
  else ++h.outside;
}

const std::vector<std::string>& bunch_columns() {
  static const std::vector<std::string> cols = {"dr_mm", "dpr_mrad", "dz_mm", "dpz_mrad", "dE_MeV", "dphase_deg"};
  return cols;
}

namespace {

/// The offsets of six standard normal variates u through the bunch's Gaussian: Twiss form
/// (e.g. Wiedemann, Particle Accelerator Physics, ch. 8) x = sqrt(eps beta) u1,
/// x' = sqrt(eps / beta) (u2 - alpha u1) in each plane (eps in mm mrad and beta in m give x in
/// mm and x' in mrad), then energy u5 and phase u6.
BunchOffset offset_of(const Bunch& b, const double (&u)[6]) {
  auto plane = [](double eps, double beta, double alpha, double u1, double u2, double& x, double& xp) {
    if (!(eps > 0)) return;
    x = std::sqrt(eps * beta) * u1;
    xp = std::sqrt(eps / beta) * (u2 - alpha * u1);
  };
  BunchOffset o;
  plane(b.emittance_r_mm_mrad, b.beta_r_m, b.alpha_r, u[0], u[1], o.dr_mm, o.dpr_mrad);
  plane(b.emittance_z_mm_mrad, b.beta_z_m, b.alpha_z, u[2], u[3], o.dz_mm, o.dpz_mrad);
  o.dE_MeV = b.sigma_E_MeV * u[4];
  o.dphase_deg = b.sigma_phase_deg * u[5];
  return o;
}

/// E[u^2] and E[u^4] of a standard normal truncated at |u| <= c (c <= 0: untruncated), by
/// Simpson's rule on the density (smooth; 2000 intervals leave ~1e-13).
void truncated_moments(double c, double& m2, double& m4) {
  if (!(c > 0)) {
    m2 = 1;
    m4 = 3;
    return;
  }
  const int n = 2000;
  const double h = 2 * c / n;
  double s0 = 0, s2 = 0, s4 = 0;
  for (int i = 0; i <= n; ++i) {
    const double u = -c + i * h, w = (i == 0 || i == n) ? 1 : (i % 2 ? 4 : 2), g = w * std::exp(-0.5 * u * u);
    s0 += g;
    s2 += g * u * u;
    s4 += g * u * u * u * u;
  }
  m2 = s2 / s0;
  m4 = s4 / s0;
}

/// The mean over centre + sum_k u_k dirs[k], u_k independent and symmetric with E[u^2] = m2,
/// E[u^4] = m4: the centre and +-a on each axis, a^2 = m4 / m2, weight m2^2 / (2 m4) each (so
/// 2 w a^2 = m2 and 2 w a^4 = m4); the centre takes the rest. Exact for every polynomial of
/// degree 5 in one variate and for odd mixed terms; it misses even mixed terms (u_j^2 u_k^2).
std::vector<QuadratureNode> axis_nodes(const BunchOffset& centre, const std::vector<BunchOffset>& dirs, double m2,
                                       double m4) {
  if (dirs.empty()) return {{centre, 1}};
  const double a = std::sqrt(m4 / m2), w = m2 * m2 / (2 * m4);
  std::vector<QuadratureNode> q;
  q.push_back({centre, 1 - 2 * w * static_cast<double>(dirs.size())});
  for (const auto& d : dirs)
    for (double sg : {1.0, -1.0}) {
      BunchOffset o = centre;
      o += scaled(d, sg * a);
      q.push_back({o, w});
    }
  return q;
}

}  // namespace

std::vector<BunchOffset> gaussian_bunch(const Bunch& b, size_t n, std::uint64_t seed) {
  std::vector<BunchOffset> out(n);
  for (size_t i = 0; i < n; ++i) {
    Normal g(seed, i);
    const double c = b.cutoff_sigma;
    double u[6];
    for (double& v : u) v = g.draw(c);
    out[i] = offset_of(b, u);
  }
  return out;
}

std::vector<QuadratureNode> bunch_quadrature(const Bunch& b) {
  double m2 = 1, m4 = 3;
  truncated_moments(b.cutoff_sigma, m2, m4);
  // Along each variate the used plane or spread moves: u_k = +-a, the rest 0.
  const bool used[6] = {b.emittance_r_mm_mrad > 0, b.emittance_r_mm_mrad > 0, b.emittance_z_mm_mrad > 0,
                        b.emittance_z_mm_mrad > 0, b.sigma_E_MeV != 0,        b.sigma_phase_deg != 0};
  std::vector<BunchOffset> dirs;
  for (int k = 0; k < 6; ++k) {
    if (!used[k]) continue;
    double u[6] = {0, 0, 0, 0, 0, 0};
    u[k] = 1;
    dirs.push_back(offset_of(b, u));
  }
  if (dirs.empty()) return {};
  return axis_nodes(BunchOffset{}, dirs, m2, m4);
}

std::vector<QuadratureNode> bunch_quadrature(const std::vector<BunchOffset>& sample) {
  if (sample.empty()) return {};
  auto fields = [](const BunchOffset& o) {
    return Eigen::Matrix<double, 6, 1>(o.dr_mm, o.dpr_mrad, o.dz_mm, o.dpz_mrad, o.dE_MeV, o.dphase_deg);
  };
  Eigen::Matrix<double, 6, 1> mean = Eigen::Matrix<double, 6, 1>::Zero();
  for (const auto& o : sample) mean += fields(o);
  mean /= static_cast<double>(sample.size());
  Eigen::Matrix<double, 6, 6> cov = Eigen::Matrix<double, 6, 6>::Zero();
  for (const auto& o : sample) {
    const Eigen::Matrix<double, 6, 1> d = fields(o) - mean;
    cov += d * d.transpose();
  }
  cov /= static_cast<double>(sample.size());
  // Principal directions (a covariance may be singular: a column a file leaves out).
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix<double, 6, 6>> es(cov);
  const double top = std::max(es.eigenvalues().maxCoeff(), 0.0);
  std::vector<BunchOffset> dirs;
  for (int k = 0; k < 6; ++k) {
    const double lambda = es.eigenvalues()(k);
    if (!(lambda > 1e-12 * top) || !(top > 0)) continue;
    const Eigen::Matrix<double, 6, 1> v = es.eigenvectors().col(k) * std::sqrt(lambda);
    dirs.push_back(BunchOffset{v(0), v(1), v(2), v(3), v(4), v(5)});
  }
  const BunchOffset centre{mean(0), mean(1), mean(2), mean(3), mean(4), mean(5)};
  return axis_nodes(centre, dirs, 1, 3);
}

BunchFile read_bunch_file(const std::string& path) {
  CsvTable t = CsvTable::read(path);
  const auto& known = bunch_columns();
  for (const auto& h : t.header())
    if (std::find(known.begin(), known.end(), h) == known.end())
      throw data_error(t.name(), 0,
                       "unknown column '" + h + "' (a bunch file has dr_mm, dpr_mrad, dz_mm, dpz_mrad, dE_MeV, dphase_deg)");
  if (t.rows() == 0) throw data_error(t.name(), 0, "no particles (the file has a header but no rows)");
  BunchFile out;
  out.name = t.name();
  out.offsets.resize(t.rows());
  double BunchOffset::*fields[] = {&BunchOffset::dr_mm, &BunchOffset::dpr_mrad, &BunchOffset::dz_mm,
                                   &BunchOffset::dpz_mrad, &BunchOffset::dE_MeV, &BunchOffset::dphase_deg};
  for (size_t c = 0; c < known.size(); ++c) {
    if (!t.has_column(known[c])) continue;
    const size_t col = t.column(known[c]);
    for (size_t i = 0; i < t.rows(); ++i) out.offsets[i].*fields[c] = t.number(i, col);
  }
  for (size_t i = 0; i < t.rows(); ++i) out.lines.push_back(t.line(i));
  return out;
}

namespace {

/// offset_state of offsets[0, count); `where(i)` says where offset i came from when it fails.
std::vector<ParticleState> start_states(const Injection& inj, double mass_MeV, double rf_MHz,
                                        const std::vector<BunchOffset>& offsets, size_t count,
                                        const std::function<Error(size_t, const Error&)>& where) {
  std::vector<ParticleState> out;
  out.reserve(count);
  for (size_t i = 0; i < count; ++i) {
    try {
      out.push_back(offset_state(inj, mass_MeV, rf_MHz, offsets[i]));
    } catch (const Error& e) {
      throw where(i, e);
    }
  }
  return out;
}

}  // namespace

std::vector<ParticleState> offset_states(const Injection& inj, double mass_MeV, double rf_MHz, const BunchFile& file,
                                         size_t count) {
  if (count == 0 || count > file.offsets.size()) count = file.offsets.size();
  return start_states(inj, mass_MeV, rf_MHz, file.offsets, count, [&](size_t i, const Error& e) {
    return data_error(file.name, file.lines[i], e.what());
  });
}

std::vector<ParticleState> offset_states(const Injection& inj, double mass_MeV, double rf_MHz,
                                         const std::vector<BunchOffset>& offsets) {
  return start_states(inj, mass_MeV, rf_MHz, offsets, offsets.size(), [](size_t i, const Error& e) {
    return Error(e.code(), std::string(e.what()) + " (particle " + std::to_string(i) + ")");
  });
}

ParticleState offset_state(const Injection& inj, double mass_MeV, double rf_MHz, const BunchOffset& o) {
  Injection in = inj;
  in.energy_MeV += o.dE_MeV;
  if (!(in.energy_MeV > 0))
    throw Error(ExitCode::data, "bunch: an energy offset of " + std::to_string(o.dE_MeV) +
                                    " MeV leaves no kinetic energy");
  in.r_mm += o.dr_mm;
  if (!(in.r_mm > 0))
    throw Error(ExitCode::data, "bunch: a radius offset of " + std::to_string(o.dr_mm) + " mm puts a particle at r <= 0");
  const double P0 = kinematics(mass_MeV, 1, inj.energy_MeV).betagamma;
  const double P = kinematics(mass_MeV, 1, in.energy_MeV).betagamma;
  in.pr_betagamma = P * (inj.pr_betagamma / P0 + o.dpr_mrad * 1e-3);
  in.z_mm += o.dz_mm;
  in.pz_betagamma = P * (inj.pz_betagamma / P0 + o.dpz_mrad * 1e-3);
  if (in.pr_betagamma * in.pr_betagamma + in.pz_betagamma * in.pz_betagamma >= P * P)
    throw Error(ExitCode::data, "bunch: angle offsets leave a particle no azimuthal momentum");
  if (o.dphase_deg != 0) {
    if (!(rf_MHz > 0)) throw Error(ExitCode::data, "bunch: a phase offset needs an RF frequency (rf.frequency_MHz)");
    in.t_ns += o.dphase_deg / (360 * rf_MHz * 1e6) * 1e9;
  }
  return injection_state(in, mass_MeV);
}

std::vector<QuadratureNode> machine_bunch_quadrature(const Machine& m, const std::string& file) {
  const std::string f = !file.empty() ? file : m.bunch ? m.bunch->file : std::string();
  if (!f.empty()) return bunch_quadrature(read_bunch_file(f).offsets);
  return m.bunch ? bunch_quadrature(*m.bunch) : std::vector<QuadratureNode>{};
}

CentroidTurns centroid_turns(const TrackModel& model, const ParticleState& reference, const Injection& inj,
                             double mass_MeV, const std::vector<QuadratureNode>& nodes, const TrackSettings& settings,
                             unsigned threads) {
  CentroidTurns out;
  const size_t n = nodes.size();
  // Each node's crossings as [probe][turn - 1] (NaN radius: not crossed).
  std::vector<std::vector<std::vector<TurnRecord>>> hit(n, std::vector<std::vector<TurnRecord>>(model.probes.size()));
  std::vector<unsigned char> started(n, 0);
  // The particles: the reference first, then every node that can start (a spread that leaves
  // no energy crosses nowhere). They are tracked in one group per thread (track_particles); a
  // particle's records do not depend on its group.
  std::vector<ParticleState> starts{reference};
  std::vector<size_t> node_of{n};  // n: the reference
  for (size_t i = 0; i < n; ++i) {
    try {
      starts.push_back(offset_state(inj, mass_MeV, model.rf_MHz, nodes[i].offset));
      node_of.push_back(i);
      started[i] = 1;
    } catch (const Error&) {
    }
  }
  const size_t np = starts.size();
  const size_t groups = std::max<size_t>(1, std::min<size_t>(std::max(1u, threads), np));
  std::vector<std::vector<TurnRecord>> turns(np);
  std::vector<TrackEnd> ends(np);
  std::vector<std::exception_ptr> error(groups);
  // A probe records only the particles that cross it within its extent, and a turn near an end
  // is seen in part. The nodes are tracked with probes of unlimited extent, so that the bunch's
  // spread across the end is known (the path does not depend on the extent: a crossing records
  // or not, nothing else), and the reference's records are kept where the real probe has them.
  TrackModel unlimited = model;
  for (auto& pl : unlimited.probes) {
    pl.s_min_m = -1e9;
    pl.s_max_m = 1e9;
  }
  parallel_for(groups, threads, [&](size_t g, unsigned) {
    const size_t first = g * np / groups, last = (g + 1) * np / groups;
    try {
      track_particles(unlimited, starts.data() + first, last - first, settings, turns.data() + first,
                      ends.data() + first);
    } catch (...) {
      error[g] = std::current_exception();
    }
  });
  for (const auto& e : error)
    if (e) std::rethrow_exception(e);
  // The reference's crossings within the extent (land_and_act's test: s - shift in [s_min, s_max]).
  for (const auto& t : turns[0]) {
    const ProbeLine& pl = model.probes[static_cast<size_t>(t.probe)];
    if (t.s_mm >= pl.s_min_m * 1e3 && t.s_mm <= pl.s_max_m * 1e3) out.reference.push_back(t);
  }
  out.end = ends[0];
  for (size_t q = 1; q < np; ++q) {
    const size_t i = node_of[q];
    for (const auto& t : turns[q]) {
      auto& v = hit[i][static_cast<size_t>(t.probe)];
      const auto k = static_cast<size_t>(t.turn - 1);
      if (v.size() <= k) {
        TurnRecord none;
        none.r_mm = std::nan("");
        v.resize(k + 1, none);
      }
      v[k] = t;
    }
  }
  out.centre = out.reference;
  out.known.assign(out.reference.size(), 0);
  for (size_t c = 0; c < out.reference.size(); ++c) {
    const TurnRecord& ref = out.reference[c];
    const auto p = static_cast<size_t>(ref.probe), k = static_cast<size_t>(ref.turn - 1);
    TurnRecord mean = ref;
    mean.r_mm = mean.s_mm = mean.t_ns = mean.energy_MeV = 0;
    double dphase = 0;
    bool all = n > 0;
    for (size_t i = 0; i < n && all; ++i) {
      all = started[i] && k < hit[i][p].size() && !std::isnan(hit[i][p][k].r_mm);
      if (!all) break;
      const TurnRecord& t = hit[i][p][k];
      const double w = nodes[i].weight;
      mean.r_mm += w * t.r_mm;
      mean.s_mm += w * t.s_mm;
      mean.t_ns += w * t.t_ns;
      mean.energy_MeV += w * t.energy_MeV;
      dphase += w * std::remainder(t.phase_deg - ref.phase_deg, 360.0);
    }
    if (!all) {
      ++out.unknown;
      continue;
    }
    // The part of the bunch the probe sees: the Gaussian with the nodes' mean and spread along
    // the probe, cut at the extent's ends, has its mean sigma (phi(a) - phi(b)) / (Phi(b) - Phi(a))
    // away (a, b the ends in sigmas from the mean); the radius follows the position along the
    // probe by the nodes' regression of one on the other. Ends more than kCutSigmas away change
    // nothing (at 5 sigmas the cut moves the mean by 1.5e-6 sigma), so turns clear of the ends
    // keep the quadrature's mean bit for bit. A bunch the probe sees less than kSeenMin of is
    // not predicted (the reference's record, as for a missed crossing).
    {
      constexpr double kCutSigmas = 5, kSeenMin = 0.05;
      double vs = 0, crs = 0;
      for (size_t i = 0; i < n; ++i) {
        const TurnRecord& t = hit[i][p][k];
        vs += nodes[i].weight * (t.s_mm - mean.s_mm) * (t.s_mm - mean.s_mm);
        crs += nodes[i].weight * (t.s_mm - mean.s_mm) * (t.r_mm - mean.r_mm);
      }
      const ProbeLine& pl = model.probes[p];
      if (vs > 0) {
        const double sd = std::sqrt(vs);
        const double a = (pl.s_min_m * 1e3 - mean.s_mm) / sd, b = (pl.s_max_m * 1e3 - mean.s_mm) / sd;
        if (a > -kCutSigmas || b < kCutSigmas) {
          const auto pdf = [](double u) { return std::exp(-0.5 * u * u) / std::sqrt(2 * kPi); };
          const auto cdf = [](double u) { return 0.5 * std::erfc(-u / std::sqrt(2.0)); };
          const double seen = cdf(b) - cdf(a);
          if (!(seen >= kSeenMin)) {
            ++out.unknown;
            continue;
          }
          const double ds = sd * (pdf(a) - pdf(b)) / seen;
          mean.s_mm += ds;
          mean.r_mm += crs / vs * ds;
        }
      }
    }
    mean.phase_deg = ref.phase_deg + dphase;
    if (mean.phase_deg > 180) mean.phase_deg -= 360;
    if (mean.phase_deg <= -180) mean.phase_deg += 360;
    out.centre[c] = mean;
    out.known[c] = 1;
  }
  return out;
}

namespace {

/// The bunch's result from its chunks' sums (merged in chunk order) and the workers' histograms.
BunchResult bunch_result(const TrackModel& model, size_t n, std::vector<Partial>& parts,
                         std::vector<std::vector<ProbeHistogram>>& hists) {
  Partial all;
  all.acc.resize(model.probes.size());
  for (auto& p : parts) merge_into(all, p);
  std::vector<ProbeHistogram>& hist = hists[0];
  for (size_t w = 1; w < hists.size(); ++w)
    for (size_t p = 0; p < hist.size(); ++p) {
      for (size_t k = 0; k < hist[p].counts.size(); ++k) hist[p].counts[k] += hists[w][p].counts[k];
      hist[p].outside += hists[w][p].outside;
    }

  BunchResult res;
  res.particles = n;
  res.particle_turns = all.turns;
  res.histograms = std::move(hist);
  res.lost = std::move(all.lost);
  for (size_t p = 0; p < all.acc.size(); ++p)
    for (size_t k = 0; k < all.acc[p].size(); ++k) {
      const Acc& a = all.acc[p][k];
      if (a.n == 0) continue;
      Centroid c;
      c.probe = static_cast<int>(p);
      c.turn = static_cast<int>(k + 1);
      c.particles = a.n;
      const double inv = 1.0 / static_cast<double>(a.n);
      c.r_mm = a.r;
      c.r_rms_mm = std::sqrt(std::max(0.0, a.m2 * inv));
      c.s_mm = a.s * inv;
      c.t_ns = a.t * inv;
      c.energy_MeV = a.e * inv;
      c.phase_deg = a.phase ? std::atan2(a.ps, a.pc) * 180 / kPi : std::nan("");
      res.centroids.push_back(c);
    }
  std::stable_sort(res.centroids.begin(), res.centroids.end(),
                   [](const Centroid& a, const Centroid& b) { return a.t_ns < b.t_ns; });
  return res;
}

/// Adds a particle's records to its chunk's sums and its worker's histograms.
void add_records(Partial& part, std::vector<ProbeHistogram>& hist, const std::vector<TurnRecord>& turns) {
  for (const auto& tr : turns) {
    auto& row = part.acc[static_cast<size_t>(tr.probe)];
    if (row.size() < static_cast<size_t>(tr.turn)) row.resize(static_cast<size_t>(tr.turn));
    row[static_cast<size_t>(tr.turn - 1)].add(tr);
    add_crossing(hist, tr);
  }
}

/// track_bunch with a collective kick: chunks of kChunk particles (one group run each) advance
/// to the next kick node on the workers, the kick is computed from every running particle, and
/// the workers apply it. A chunk's records are added to its sums after every advance, in lane
/// order, so the sums do not depend on the thread count.
BunchResult track_bunch_collective(const TrackModel& model, const std::vector<ParticleState>& starts,
                                   const TrackSettings& settings, unsigned threads,
                                   const std::function<void(size_t)>& progress, const CrossingSink& sink,
                                   const CollectiveKick& ck) {
  static_assert(kChunk <= static_cast<size_t>(detail::kMaxLanes), "a chunk is one group run");
  if (settings.integrator != "azimuth" || settings.reference_stepper)
    throw usage_error("collective forces (space charge) need the azimuth integrator's group stepper, not '" +
                      settings.integrator + (settings.reference_stepper ? "' with the reference stepper" : "'"));
  if (ck.every_nodes < 1) throw usage_error("collective kick interval must be at least one step");
  const size_t n = starts.size(), nchunks = (n + kChunk - 1) / kChunk;
  if (n == 0) {
    std::vector<Partial> parts;
    std::vector<std::vector<ProbeHistogram>> hists(1, empty_histograms(model));
    return bunch_result(model, 0, parts, hists);
  }
  const double th0 = std::atan2(starts[0].y, starts[0].x);
  for (size_t i = 1; i < n; ++i)
    if (std::atan2(starts[i].y, starts[i].x) != th0)
      throw usage_error("collective forces (space charge): particle " + std::to_string(i) +
                        " starts at another azimuth than particle 0 (a bunch starts at one)");
  const unsigned nt = std::max(1u, std::min<unsigned>(threads, static_cast<unsigned>(nchunks)));
  std::vector<Partial> parts(nchunks);
  std::vector<std::vector<ProbeHistogram>> hists(nt, empty_histograms(model));
  std::vector<std::vector<TurnRecord>> turns(n);
  std::vector<TrackEnd> ends(n);
  std::vector<detail::GroupOutput> outs(n);
  for (size_t i = 0; i < n; ++i) outs[i] = {&turns[i], nullptr, nullptr, &ends[i]};
  std::vector<detail::AzimuthGroupRun> runs;
  runs.reserve(nchunks);
  for (size_t c = 0; c < nchunks; ++c) {
    const size_t first = c * kChunk, count = std::min(n, first + kChunk) - first;
    runs.emplace_back(model, starts.data() + first, count, settings, outs.data() + first);
    parts[c].acc.resize(model.probes.size());
  }
  // The kick at a node stands for half the azimuth stepped since the last kick and half the
  // azimuth to the next (a leapfrog with steps of every_nodes grid steps; the first and last
  // intervals may be shorter, from the injection azimuth to the grid and to the end).
  const double th_begin = runs[0].azimuth(), span = runs[0].end_azimuth() - th_begin;
  std::vector<size_t> index;
  std::vector<LaneState> states;
  std::vector<double> dp;
  std::vector<std::vector<size_t>> where(nchunks);  // per chunk: lane -> place in index (or none)
  const size_t none = static_cast<size_t>(-1);
  double before = 0;  // azimuth stepped since the last kick
  // Each lane's state in its particle's slot (on the workers), then the running ones packed in
  // particle order.
  std::vector<LaneState> slot(n);
  std::vector<unsigned char> alive(n);
  while (runs[0].running()) {
    parallel_for(nchunks, nt, [&](size_t c, unsigned) {
      for (size_t l = 0; l < runs[c].size(); ++l) alive[c * kChunk + l] = runs[c].lane(l, slot[c * kChunk + l]);
    });
    index.clear();
    states.clear();
    for (size_t c = 0; c < nchunks; ++c) {
      where[c].assign(runs[c].size(), none);
      for (size_t l = 0; l < runs[c].size(); ++l) {
        const size_t i = c * kChunk + l;
        if (!alive[i]) continue;
        where[c][l] = index.size();
        index.push_back(i);
        states.push_back(slot[i]);
      }
    }
    if (index.empty()) break;
    const double th = runs[0].azimuth(), after = runs[0].azimuth_after(ck.every_nodes) - th;
    dp.assign(3 * index.size(), 0.0);
    ck.kick(th, 0.5 * (before + after), index, states, dp);
    parallel_for(nchunks, nt, [&](size_t c, unsigned w) {
      detail::AzimuthGroupRun& run = runs[c];
      for (size_t l = 0; l < run.size(); ++l) {
        const size_t k = where[c][l];
        if (k != none) run.kick(l, dp[3 * k], dp[3 * k + 1], dp[3 * k + 2]);
      }
      run.advance(ck.every_nodes);
      if (sink) return;  // the records stay with their particles until the end
      for (size_t l = 0; l < run.size(); ++l) {
        std::vector<TurnRecord>& t = turns[c * kChunk + l];
        add_records(parts[c], hists[w], t);
        t.clear();
      }
    });
    before = runs[0].azimuth() - th;
    if (progress && span > 0)
      progress(static_cast<size_t>(static_cast<double>(n) * std::min(1.0, (runs[0].azimuth() - th_begin) / span)));
  }
  // Runs whose particles were all lost stop where they are; the others are at the end.
  parallel_for(nchunks, nt, [&](size_t c, unsigned w) {
    detail::AzimuthGroupRun& run = runs[c];
    while (run.advance(1 << 20)) {
    }
    run.finish();
    for (size_t l = 0; l < run.size(); ++l) {
      const size_t i = c * kChunk + l;
      add_records(parts[c], hists[w], turns[i]);
      parts[c].turns += ends[i].turns;
      if (ends[i].lost) parts[c].lost.emplace_back(i, ends[i]);
    }
  });
  if (sink)
    for (size_t i = 0; i < n; ++i) sink(i, turns[i]);
  if (progress) progress(n);
  return bunch_result(model, n, parts, hists);
}

}  // namespace

BunchResult track_bunch(const TrackModel& model, const std::vector<ParticleState>& starts,
                        const TrackSettings& settings, unsigned threads,
                        const std::function<void(size_t)>& progress, const CrossingSink& sink,
                        const CollectiveKick* collective) {
  if (collective && collective->kick)
    return track_bunch_collective(model, starts, settings, threads, progress, sink, *collective);
  const size_t n = starts.size(), nchunks = (n + kChunk - 1) / kChunk;
  std::vector<Partial> parts(nchunks);
  const unsigned nt = std::max(1u, std::min<unsigned>(threads, static_cast<unsigned>(std::max<size_t>(nchunks, 1))));
  std::vector<std::vector<ProbeHistogram>> hists(nt, empty_histograms(model));  // per worker
  std::atomic<size_t> done{0};
  // Per worker: one record list and end per particle of a chunk.
  std::vector<std::vector<std::vector<TurnRecord>>> scratch(nt, std::vector<std::vector<TurnRecord>>(kChunk));
  std::vector<std::vector<TrackEnd>> end_scratch(nt, std::vector<TrackEnd>(kChunk));
  parallel_for(nchunks, nt, [&](size_t c, unsigned w) {
    std::vector<std::vector<TurnRecord>>& turns = scratch[w];
    Partial& part = parts[c];
    part.acc.resize(model.probes.size());
    const size_t first = c * kChunk, last = std::min(n, first + kChunk);
    // The chunk's particles stepped together (track_particles); each one's records are what
    // it alone would give, so the sums below do not depend on the grouping or the threads.
    std::vector<TurnRecord>* lane_turns = turns.data();
    TrackEnd* ends = end_scratch[w].data();
    for (size_t i = first; i < last; ++i) lane_turns[i - first].clear();
    track_particles(model, starts.data() + first, last - first, settings, lane_turns, ends);
    for (size_t i = first; i < last; ++i) {
      const std::vector<TurnRecord>& turns = lane_turns[i - first];
      TrackEnd end = std::move(ends[i - first]);
      part.turns += end.turns;
      for (const auto& tr : turns) {
        auto& row = part.acc[static_cast<size_t>(tr.probe)];
        if (row.size() < static_cast<size_t>(tr.turn)) row.resize(static_cast<size_t>(tr.turn));
        row[static_cast<size_t>(tr.turn - 1)].add(tr);
        add_crossing(hists[w], tr);
      }
      if (sink) sink(i, turns);
      if (end.lost) part.lost.emplace_back(i, std::move(end));
    }
    const size_t d = done.fetch_add(last - first) + (last - first);
    if (progress) progress(d);
  });

  return bunch_result(model, n, parts, hists);
}

}  // namespace turnfit
