// turnfit: git-style dispatcher, `turnfit TOOL ARGS...` runs `turnfit-TOOL ARGS...`.
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <iostream>
#include <string>
#include <vector>

#include "turnfit/version.hpp"

namespace {

const char* const kTools[][2] = {
    {"orbit", "equilibrium orbits, tunes and isochronism of a field map"},
    {"track", "accelerated orbits: where each turn crosses each probe"},
    {"synth", "synthetic probe profiles and trim coil phase scans from a truth machine"},
    {"peakfind", "the turns in a probe profile: positions, heights, widths, flags"},
    {"compare", "measured vs simulated turn radii: errors per probe, objectives, exit 0/1 like diff"},
    {"tc-fit", "rational fits of trim coil phase-shift scans: normalized field profiles"},
    {"plot", "figures (PNG, SVG) of profiles and peaks, turn separation, residuals, trim coil fits"},
    {"nsga", "NSGA-II with constraints: threads or MPI, population log that resumes a killed run"},
    {"localsearch", "fit a turn-pattern problem's design variables: Levenberg-Marquardt, uncertainties"},
    {"diagnose", "what physics the model lacks: locate the mismatch, name the effect, refit"},
    {"import-opal", "an OPAL-cycl input as a turnfit machine, with every unused line explained"},
    {"export-opal", "a turnfit machine (and a fit) as an OPAL-cycl input that imports back"},
};

void usage(std::ostream& os) {
  os << "Usage: turnfit TOOL [ARGS...]\n"
        "       turnfit --help | --version\n\n"
        "Runs turnfit-TOOL with ARGS. Tools:\n";
  for (const auto& t : kTools) os << "  " << t[0] << std::string(12 - std::strlen(t[0]), ' ') << t[1] << "\n";
  os << "\n'turnfit TOOL --help' shows a tool's options.\n";
}

/// Folder of this executable, so installed and build-tree tools are found first.
std::string self_dir() {
  std::vector<char> buf(4096);
  ssize_t n = ::readlink("/proc/self/exe", buf.data(), buf.size() - 1);
  if (n <= 0) return {};
  std::string p(buf.data(), static_cast<size_t>(n));
  auto slash = p.rfind('/');
  return slash == std::string::npos ? std::string() : p.substr(0, slash);
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2) {
    usage(std::cerr);
    return 64;
  }
  std::string tool = argv[1];
  if (tool == "--help" || tool == "-h" || tool == "help") {
    usage(std::cout);
    return 0;
  }
  if (tool == "--version") {
    std::cout << "turnfit " << turnfit::kVersion << "\n";
    return 0;
  }
  if (tool.empty() || tool[0] == '-' || tool.find('/') != std::string::npos) {
    std::cerr << "turnfit: '" << tool << "' is not a tool name\n";
    usage(std::cerr);
    return 64;
  }
  std::string exe = "turnfit-" + tool;
  std::vector<char*> args;
  args.push_back(exe.data());
  for (int i = 2; i < argc; ++i) args.push_back(argv[i]);
  args.push_back(nullptr);
  std::string dir = self_dir();
  if (!dir.empty()) {
    std::string full = dir + "/" + exe;
    if (::access(full.c_str(), X_OK) == 0) {
      ::execv(full.c_str(), args.data());
      std::cerr << "turnfit: " << full << ": " << std::strerror(errno) << "\n";
      return 70;
    }
  }
  ::execvp(exe.c_str(), args.data());
  if (errno == ENOENT) {
    std::cerr << "turnfit: '" << tool << "' is not a turnfit tool (no " << exe << " found)\n";
    usage(std::cerr);
    return 64;
  }
  std::cerr << "turnfit: " << exe << ": " << std::strerror(errno) << "\n";
  return 70;
}
