// turnfit-export-opal's writing of a turnfit machine as OPAL-cycl commands.
#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <set>
#include <sstream>

#include "turnfit/field/map_io.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/io/text.hpp"
#include "turnfit/opal/annotation.hpp"
#include "turnfit/opal/opal_io.hpp"
#include "turnfit/trimcoil/trimcoil.hpp"
#include "turnfit/version.hpp"

namespace turnfit {
namespace {

using nlohmann::json;

// The shortest decimal that reads back as v (50.65, not 50.649999999999999).
std::string num(double v) {
  char buf[40];
  for (int digits = 6; digits <= 17; ++digits) {
    std::snprintf(buf, sizeof buf, "%.*g", digits, v);
    if (std::strtod(buf, nullptr) == v) return buf;
  }
  return format_exact(v);
}

// OPAL labels: a letter, then letters, digits, '_' and '.'; unique regardless of case.
class Labels {
 public:
  std::string make(const std::string& name) {
    std::string l;
    for (char c : name) l += (std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '.') ? c : '_';
    if (l.empty() || !std::isalpha(static_cast<unsigned char>(l[0]))) l = "E" + l;
    if (opal::reserved(opal::upper(l))) l += "_";
    std::string base = l;
    for (int k = 2; used_.count(opal::upper(l)); ++k) l = base + "_" + std::to_string(k);
    used_.insert(opal::upper(l));
    return l;
  }

 private:
  std::set<std::string> used_;
};

std::string quoted(const std::string& s, const std::string& what) {
  if (s.find('"') != std::string::npos || s.find('\n') != std::string::npos || s.find('\\') != std::string::npos)
    throw data_error(what, 0, "the name " + quote(s) + " cannot be written as an OPAL string (quote, backslash or newline)");
  return "\"" + s + "\"";
}

std::string list(const std::vector<double>& v) {
  std::string s;
  for (double x : v) s += (s.empty() ? "" : ", ") + num(x);
  return "{" + s + "}";
}

}  // namespace

std::string export_opal(const Machine& m, const std::string& out_dir, const std::string& map_file,
                        const std::string& dist_file, std::vector<std::string>& warnings) {
  const std::string mname = m.path.empty() ? std::string("machine") : m.path;
  if (!m.injection)
    throw data_error(mname, 0, "/injection: missing: OPAL-cycl needs the start (RINIT, PHIINIT, the beam's energy)");
  if (!(m.rf.frequency_MHz > 0) && !m.cavities.empty())
    throw data_error(mname, 0, "/rf/frequency_MHz: cavities need an RF frequency");
  const Injection& inj = *m.injection;
  Labels labels;
  const std::string ring = labels.make("Ring"), line = labels.make("L1"), beam = labels.make("Beam1"),
                    dist = labels.make("Dist1"), fs1 = labels.make("Fs1");
  std::ostringstream os;
  os << "// OPAL-cycl input written by turnfit-export-opal " << kVersion << " from the turnfit machine "
     << quote(m.name.empty() ? mname : m.name) << ".\n"
     << "// Run OPAL in this file's folder: the file names below are relative to it. Physics that OPAL\n"
     << "// does not have travels in the turnfit annotation at the end (comments to OPAL).\n";
  os << "\nOPTION, VERSION = 20220100;\nOPTION, ECHO = FALSE;\n";
  os << "TITLE, STRING = " << quoted(m.name.empty() ? "turnfit machine" : m.name, mname) << ";\n\n";

  // Trim coils.
  std::vector<std::string> coil_labels;
  for (size_t i = 0; i < m.trimcoils.size(); ++i) {
    const TrimCoil& t = m.trimcoils[i];
    const std::string where = "/trimcoils/" + std::to_string(i);
    if (t.type == "table")
      throw data_error(mname, 0, where + ": trim coil " + quote(t.name) + " is a table, which OPAL has no type for");
    if (!t.sectors.empty())
      warnings.push_back("trim coil " + quote(t.name) + " sits on sectors of its own; OPAL spreads it over every sector");
    const std::string l = labels.make(t.name);
    coil_labels.push_back(l);
    os << l << ": TRIMCOIL, TYPE = ";
    if (t.type == "psi-bfield-mirrored") {
      os << "\"PSI-BFIELD-MIRRORED\", RMIN = " << num(t.rmin_mm) << ", RMAX = " << num(t.rmax_mm)
         << ", BMAX = " << num(t.bmax_T) << ", SLPTC = " << num(t.slope_per_mm);
    } else {
      std::vector<double> cn = t.coefnum, cd = t.coefdenom;
      if (t.coef_origin_mm != 0) {
        // OPAL's polynomials are in r itself: expand p(r - origin) (long double).
        auto expand = [&](const std::vector<double>& c) {
          std::vector<long double> lc(c.begin(), c.end());
          auto s = taylor_shift(lc, -static_cast<long double>(t.coef_origin_mm) * 1e-3L);
          return std::vector<double>(s.begin(), s.end());
        };
        cn = expand(cn);
        if (!cd.empty()) cd = expand(cd);
        warnings.push_back("trim coil " + quote(t.name) + ": coefficients about r = " + num(t.coef_origin_mm) +
                           " mm are expanded to OPAL's polynomials in r");
      }
      os << (t.type == "psi-phase" ? "\"PSI-PHASE\"" : "\"PSI-BFIELD\"") << ", RMIN = " << num(t.rmin_mm)
         << ", RMAX = " << num(t.rmax_mm) << ", BMAX = " << num(t.bmax_T == 0 ? 0.0 : -t.bmax_T) << ",\n    COEFNUM = " << list(cn);
      if (!cd.empty()) os << ",\n    COEFDENOM = " << list(cd);
    }
    // OPAL 2022.1 needs the window written out (unset, a coil acts at azimuth 0 alone); a
    // window through azimuth 0 is PHIMIN > PHIMAX there.
    const double width = std::min(t.phimax_deg - t.phimin_deg, 360.0);
    double lo = width >= 360 ? 0 : std::fmod(t.phimin_deg, 360.0);
    if (lo < 0) lo += 360;
    double hi = lo + width;
    if (hi > 360) hi -= 360;
    os << ",\n    PHIMIN = " << num(lo) << ", PHIMAX = " << num(hi) << ";\n";
  }
  if (!m.trimcoils.empty()) os << "\n";

  // The cyclotron.
  std::string map = map_file;
  if (map.empty()) {
    if (m.field.format != "psi-ring")
      throw usage_error("the machine's field map is in turnfit's format, which OPAL cannot read: give --map-out FILE "
                        "to write it in OPAL's RING format");
    map = relative_to(m.field.map, out_dir);
  }
  os << ring << ": CYCLOTRON, TYPE = \"RING\", FMAPFN = " << quoted(map, mname);
  // OPAL's SYMMETRY has no default: a machine that takes it from the map gets the map's. OPAL
  // 2022.1 starts a RING map at azimuth 0 whatever its header says (physics.md).
  const PolarGrid grid = read_field_map(m.field.map, parse_map_format(m.field.format), m.field.symmetry).grid();
  const int symmetry = m.field.symmetry > 0 ? m.field.symmetry : grid.symmetry;
  if (grid.theta_min_deg != 0)
    warnings.push_back("the map starts at azimuth " + num(grid.theta_min_deg) +
                       " deg; OPAL 2022.1 starts every RING map at 0, so OPAL's field is turned by that much");
  os << ", SYMMETRY = " << symmetry;
  if (m.field.scale != 1) os << ", BSCALE = " << num(m.field.scale);
  os << ",\n    CYHARMON = " << m.rf.harmonic << ", RFFREQ = " << num(m.rf.frequency_MHz) << ",\n    RINIT = "
     << num(inj.r_mm) << ", PRINIT = " << num(inj.pr_betagamma) << ", PHIINIT = " << num(inj.phi_deg);
  if (inj.z_mm != 0 || inj.pz_betagamma != 0)
    os << ", ZINIT = " << num(inj.z_mm) << ", PZINIT = " << num(inj.pz_betagamma);
  if (m.field.trimcoil_threshold_T != 0) os << ",\n    TRIMCOILTHRESHOLD = " << num(m.field.trimcoil_threshold_T);
  if (!coil_labels.empty()) {
    os << ",\n    TRIMCOIL = {";
    for (size_t i = 0; i < coil_labels.size(); ++i) os << (i ? ", " : "") << coil_labels[i];
    os << "}";
  }
  os << ";\n";
  if (inj.t_ns != 0) warnings.push_back("injection t_ns (" + num(inj.t_ns) + " ns) has no OPAL equivalent: OPAL starts at t = 0");

  // Cavities and probes, in the machine's order.
  std::vector<std::string> members{ring};
  for (const Cavity& c : m.cavities) {
    const std::string l = labels.make(c.name);
    members.push_back(l);
    os << l << ": RFCAVITY, TYPE = \"SINGLEGAP\", VOLT = " << num(c.voltage_MV);
    if (!c.profile.empty()) os << ", FMAPFN = " << quoted(relative_to(c.profile, out_dir), mname);
    else warnings.push_back("cavity " + quote(c.name) + " has no voltage profile (flat): OPAL's SINGLEGAP needs FMAPFN");
    os << ",\n    FREQ = " << num(c.harmonic_factor * m.rf.frequency_MHz) << ", PHI0 = " << num(c.phase_deg)
       << ", ANGLE = " << num(c.angle_deg) << ", PDIS = " << num(c.pdis_mm) << ",\n    RMIN = "
       << num(c.rmin_mm + c.rshift_mm) << ", RMAX = " << num(c.rmax_mm + c.rshift_mm)
       << ", GAPWIDTH = " << num(c.gap_width_mm) << ";\n";
  }
  for (const Probe& p : m.probes) {
    const std::string l = labels.make(p.name);
    members.push_back(l);
    const double ph = p.phi_deg * M_PI / 180, c = std::cos(ph), s = std::sin(ph);
    const double s0 = p.s_min_mm + p.shift_mm, s1 = p.s_max_mm + p.shift_mm;
    os << l << ": PROBE, XSTART = " << num(s0 * c + p.a_mm * s) << ", YSTART = " << num(s0 * s - p.a_mm * c)
       << ",\n    XEND = " << num(s1 * c + p.a_mm * s) << ", YEND = " << num(s1 * s - p.a_mm * c)
       << ", STEP = " << num(p.step_mm) << ";\n";
  }
  os << "\n" << line << ": LINE = (";
  for (size_t i = 0; i < members.size(); ++i) os << (i ? ", " : "") << members[i];
  os << ");\n\n";

  // Beam, distribution, solver, tracking.
  const double mass = m.particle.mass_MeV, E = inj.energy_MeV;
  const double pc_GeV = std::sqrt(E * (E + 2 * mass)) * 1e-3;
  os << beam << ": BEAM, ";
  static const std::map<std::string, std::string> opal_particle = {
      {"proton", "PROTON"}, {"deuteron", "DEUTERON"}, {"alpha", "ALPHA"}, {"h2+", "H2P"}};
  auto op = opal_particle.find(m.particle.species);
  if (op != opal_particle.end()) os << "PARTICLE = " << op->second;
  else os << "MASS = " << num(mass * 1e-3) << ", CHARGE = " << num(m.particle.charge_e);
  os << ", PC = " << num(pc_GeV) << ", NPART = 1, BCURRENT = 1.0E-6";
  if (m.rf.frequency_MHz > 0) os << ", BFREQ = " << num(m.rf.frequency_MHz);
  os << ";\n";
  os << dist << ": DISTRIBUTION, TYPE = FROMFILE, FNAME = " << quoted(dist_file, mname) << ";\n";
  os << fs1 << ": FIELDSOLVER, FSTYPE = NONE, MX = 8, MY = 8, MT = 8, PARFFTX = TRUE, PARFFTY = TRUE, "
            "PARFFTT = FALSE,\n    BCFFTX = OPEN, BCFFTY = OPEN, BCFFTT = OPEN;\n\n";
  if (m.bunch) warnings.push_back("the machine's bunch is not written as an OPAL distribution (one particle at the reference)");
  if (!m.effect_set.empty())
    warnings.push_back("the machine's effects (" + std::to_string(m.effects.size()) +
                       ") have no OPAL equivalent: OPAL tracks without them");
  const int spt = m.tracking.steps_per_turn > 0 ? m.tracking.steps_per_turn : 2880;
  int turns = m.tracking.turns;
  if (turns <= 0) {
    turns = 1000;
    warnings.push_back("tracking.turns is 0 (until loss): OPAL needs MAXSTEPS, written for 1000 turns");
  }
  os << "TRACK, LINE = " << line << ", BEAM = " << beam << ", MAXSTEPS = " << static_cast<long long>(turns) * spt
     << ", STEPSPERTURN = " << spt << ";\n";
  os << "RUN, METHOD = \"CYCLOTRON-T\", BEAM = " << beam << ", FIELDSOLVER = " << fs1 << ", DISTRIBUTION = " << dist
     << ";\nENDTRACK;\n";
  std::string text = os.str();

  // The annotation: what the commands import to, and the machine itself. An export its own
  // import refuses is a machine OPAL's commands cannot carry: say which.
  auto read_back = [&](const std::string& t) {
    try {
      return import_opal(t, mname + " (as OPAL commands)", out_dir, out_dir, kDefaultOpalVersion, false);
    } catch (const Error& e) {
      throw data_error(mname, 0, std::string("cannot be written for OPAL: ") + e.what());
    }
  };
  json opal_part = read_back(text).machine;
  json machine = m.doc;
  rebase_paths(machine, m.dir, out_dir);
  text += "\nSTOP;\n\n// turnfit annotation (turnfit-export-opal): the machine as turnfit has it. turnfit-import-opal\n"
          "// restores it from these lines while the commands above are unchanged; OPAL reads them as comments.\n";
  text += write_annotation(opal_part, machine);
  // The header's notes: what OPAL will do differently.
  std::string head;
  for (const auto& w : warnings) head += "// note: " + w + "\n";
  const size_t at = text.find("\nOPTION, VERSION");
  text.insert(at, head.empty() ? std::string() : head);
  // The whole file, notes and annotation included, must read back as this machine.
  const OpalImport whole = read_back(text);
  if (!whole.from_annotation)
    throw Error(ExitCode::software, "turnfit-export-opal: the input written for " + quote(mname) +
                                        " does not read back as the machine (an export bug)");
  return text;
}

}  // namespace turnfit
