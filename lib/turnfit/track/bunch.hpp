// Bunches: many particles around the injection point, tracked on all threads, reduced to
// per-turn centroids and to histograms along each probe (simulated probe profiles).
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "turnfit/machine/machine.hpp"
#include "turnfit/track/tracker.hpp"

namespace turnfit {

/// One particle's offsets from the injection point (the reference particle has all zeros).
struct BunchOffset {
  double dr_mm = 0;       ///< radius
  double dpr_mrad = 0;    ///< radial angle p_r / p
  double dz_mm = 0;       ///< height
  double dpz_mrad = 0;    ///< vertical angle p_z / p
  double dE_MeV = 0;      ///< kinetic energy
  double dphase_deg = 0;  ///< RF phase: positive starts later (dt = dphase / (360 f_rf))
};

/// Offsets added coordinate by coordinate, and scaled by f.
BunchOffset& operator+=(BunchOffset& a, const BunchOffset& b);
BunchOffset scaled(const BunchOffset& d, double f);

/// The columns a bunch file may have (any subset, at least one; absent columns are 0).
const std::vector<std::string>& bunch_columns();

/// Draws n offsets from the bunch's Gaussian. Particle i depends only on (seed, i), so a run
/// gives the same particles whatever the thread count, and n + 1 particles extend n.
std::vector<BunchOffset> gaussian_bunch(const Bunch& b, size_t n, std::uint64_t seed);

/// A weighted point of a bunch quadrature: sum_k weight_k f(offset_k) approximates the mean of
/// f over the bunch.
struct QuadratureNode {
  BunchOffset offset;
  double weight = 0;
};

/// A quadrature of the bunch's Gaussian for smooth f: the centre and +-a along each standard
/// normal variate the bunch spreads (the radial and vertical planes two each, energy, phase),
/// a and the weights matching the second and fourth moments of the variate truncated at
/// cutoff_sigma (untruncated: a = sqrt 3, weight 1/6; the centre takes the rest, negative
/// beyond three variates). Exact for every polynomial of degree 5 in one variate and for odd
/// mixed terms; it leaves out even mixed terms such as u_E^2 u_phase^2. On ring8's bunch (2 deg,
/// 30 keV, 1 mm mrad) those change the centroid by 1.2e-4 mm rms (Stroud's degree-5 rule with
/// every pair: 73 particles instead of 13), and 144-point polar rules per plane agree with it
/// to 1e-5 mm (radial) and 1.2e-4 mm (energy and phase). Empty when the bunch has no spread.
std::vector<QuadratureNode> bunch_quadrature(const Bunch& b);

/// The same quadrature for a sample of offsets (a bunch file): the Gaussian with the sample's
/// mean and covariance, its variates along the covariance's principal axes (directions without
/// spread are left out).
std::vector<QuadratureNode> bunch_quadrature(const std::vector<BunchOffset>& sample);

/// The quadrature of the bunch a machine tracks: of the offsets in `file` when one is given,
/// else of its bunch block's file, else of its bunch block's Gaussian; empty when there is no
/// bunch with spread. Errors reading a file name it and its line.
std::vector<QuadratureNode> machine_bunch_quadrature(const Machine& m, const std::string& file = "");

/// The bunch's centre at each crossing of the reference particle, by a quadrature.
struct CentroidTurns {
  std::vector<TurnRecord> reference;  ///< the reference particle's crossings
  std::vector<TurnRecord> centre;     ///< the same crossings, every column the quadrature's mean
  std::vector<unsigned char> known;   ///< per crossing: 1 where every node crossed there too (at any s)
  size_t unknown = 0;                 ///< crossings some node missed, or seen < 5 %: centre = reference there
  TrackEnd end;                       ///< how the reference particle's track ended
};

/// Tracks the reference particle from `reference` and every node of `nodes` (offset from `inj`
/// as offset_state does) on `threads` threads, and averages each crossing (probe, turn) over the
/// nodes with their weights: r, s, t and energy directly, the phase as the reference's plus the
/// mean of each node's difference to it, wrapped to (-180, 180]. A probe sees only the part of
/// the bunch within its extent: where the nodes' spread along the probe (as a Gaussian) reaches
/// within 5 sigmas of an end, r and s are the mean of the part inside (the truncated Gaussian's
/// mean, r following s by the nodes' regression; t, energy and phase stay the whole bunch's).
/// Where a node missed the crossing (lost, short of the last turn, or unable to start), or the
/// probe sees less than 5 % of the bunch, the centre is the reference's record. Throws what
/// tracking any of them throws (the steppers report losses instead; what is left is running out
/// of memory).
CentroidTurns centroid_turns(const TrackModel& model, const ParticleState& reference, const Injection& inj,
                             double mass_MeV, const std::vector<QuadratureNode>& nodes, const TrackSettings& settings,
                             unsigned threads);

/// Offsets read from a bunch file, with the line each came from.
struct BunchFile {
  std::string name;                 ///< the file as messages name it ("<stdin>" for "-")
  std::vector<BunchOffset> offsets;  ///< one per row
  std::vector<long> lines;          ///< each row's line in the file
};

/// Reads offsets from a CSV file with a header of bunch_columns() names ("-" for stdin);
/// errors name the file and line.
BunchFile read_bunch_file(const std::string& path);

/// The start state of a particle at `o` from the injection point. rf_MHz converts the phase
/// offset to time (EX_DATAERR if a phase offset is asked for without RF).
ParticleState offset_state(const Injection& inj, double mass_MeV, double rf_MHz, const BunchOffset& o);

/// offset_state of the first `count` offsets of `file` (all for 0). An offset no particle can
/// start from (no energy left, no forward momentum) is an error naming the file and its line.
std::vector<ParticleState> offset_states(const Injection& inj, double mass_MeV, double rf_MHz, const BunchFile& file,
                                         size_t count = 0);
/// The same for offsets drawn, not read: an error names the particle's index.
std::vector<ParticleState> offset_states(const Injection& inj, double mass_MeV, double rf_MHz,
                                         const std::vector<BunchOffset>& offsets);

/// Counts of probe crossings along a probe, in bins of the probe's step over the recorded
/// radii (turns.csv's r_mm) the probe spans.
struct ProbeHistogram {
  double lo_mm = 0;    ///< lower edge of the first bin (the recorded radius at s_min)
  double step_mm = 0;  ///< bin width (the probe's step)
  std::vector<std::uint64_t> counts;
  std::uint64_t outside = 0;  ///< crossings recorded outside the bins (none for a plain probe)
};

/// Empty histograms, one per probe of the model: bins of the probe's step over its extent.
std::vector<ProbeHistogram> empty_histograms(const TrackModel& model);

/// Counts one probe crossing (its recorded radius) in its probe's histogram.
void add_crossing(std::vector<ProbeHistogram>& h, const TurnRecord& tr);

/// The bunch at one crossing of one probe: means over the particles that crossed.
struct Centroid {
  int probe = 0;
  int turn = 0;
  std::uint64_t particles = 0;
  double r_mm = 0, r_rms_mm = 0, s_mm = 0, t_ns = 0, energy_MeV = 0;
  double phase_deg = 0;  ///< circular mean; NaN without RF
};

/// What a bunch run produced.
struct BunchResult {
  std::vector<Centroid> centroids;            ///< in the order of their mean time
  std::vector<ProbeHistogram> histograms;     ///< one per probe of the model
  std::vector<std::pair<size_t, TrackEnd>> lost;  ///< index and end of every lost particle
  size_t particles = 0;
  double particle_turns = 0;                  ///< revolutions tracked, summed over particles
};

/// Receives each particle's probe crossings (its index and its records in time order), for
/// callers that need more than centroids and histograms (turnfit-synth's wire signals).
using CrossingSink = std::function<void(size_t particle, const std::vector<TurnRecord>& turns)>;

/// What acts on a bunch's particles together (space charge: spacecharge/space_charge.hpp). The
/// particles are stepped in azimuth together, and every `every_nodes` grid nodes of the azimuth
/// integrator (and once at the start) `kick` is given the states of the particles still running
/// (`index` their places in the bunch, `states` theirs, all at one azimuth `theta_rad`) and the
/// azimuth `dtheta_rad` the kick stands for; it writes each one's momentum change dp[3 i ..
/// 3 i + 2] [m c, lab x y z]. (The kick at the start stands for half an interval, the others for
/// a whole one: kick, step, kick, as a leapfrog.)
struct CollectiveKick {
  long every_nodes = 1;
  std::function<void(double theta_rad, double dtheta_rad, const std::vector<size_t>& index,
                      const std::vector<LaneState>& states, std::vector<double>& dp)>
      kick;
};

/// Tracks every start state on `threads` threads. Results do not depend on the thread count
/// (particles are reduced in fixed chunks, merged in order). `progress`, if given, is called
/// from worker threads with the number of particles done. `sink`, if given, is called from
/// worker threads, concurrently for different particles, once per particle.
/// With `collective` (and its kick set), the particles go through the azimuth integrator's grid
/// nodes together and are kicked between them (EX_USAGE for another integrator or the reference
/// stepper; every start must be at one azimuth, as a bunch's are); its records are reduced as
/// they come, so memory does not grow with the turns unless a sink keeps them.
BunchResult track_bunch(const TrackModel& model, const std::vector<ParticleState>& starts,
                        const TrackSettings& settings, unsigned threads,
                        const std::function<void(size_t)>& progress = {}, const CrossingSink& sink = {},
                        const CollectiveKick* collective = nullptr);

}  // namespace turnfit
