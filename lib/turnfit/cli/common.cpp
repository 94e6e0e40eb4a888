// Shared CLI behaviour: option block, exit-code mapping, provenance, warnings.
#include "turnfit/cli/common.hpp"

#include <unistd.h>

#include <cstdio>
#include <iostream>
#include <new>

#include "turnfit/io/error.hpp"
#include "turnfit/io/interrupt.hpp"
#include "turnfit/io/limits.hpp"
#include "turnfit/io/parallel.hpp"
#include "turnfit/version.hpp"

namespace turnfit::cli {
namespace {
std::string g_tool;
std::vector<std::string> g_argv;
bool g_have_provenance = false;
}  // namespace

void add_common_options(CLI::App& app, CommonOptions& opts, unsigned which,
                        const std::vector<std::string>& formats) {
  if (which & kOutput)
    app.add_option("-o,--output", opts.output, "Output file ('-' for stdout)")->capture_default_str();
  if ((which & kFormat) && !formats.empty()) {
    opts.format = formats.front();
    app.add_option("--format", opts.format, "Output format")
        ->check(CLI::IsMember(formats))
        ->capture_default_str();
  }
  if (which & kThreads)
    app.add_option("--threads", opts.threads, "Worker threads (0: all cores)")->capture_default_str();
  if (which & kSeed) app.add_option("--seed", opts.seed, "Random seed")->capture_default_str();
  app.add_flag("-q,--quiet", opts.quiet, "No warnings or progress on stderr");
  app.add_flag("--no-provenance", opts.no_provenance,
               "Leave out the tool/version/argv record (for reproducible golden files)");
}

int run_tool(const std::string& tool, CLI::App& app, int argc, char** argv,
             const std::function<int()>& body) {
  const std::string prog = "turnfit-" + tool;
  g_tool = prog;
  g_argv.assign(argv, argv + argc);
  g_have_provenance = true;
  app.name(prog);
  app.set_version_flag("--version", prog + " " + kVersion);
  // --help and --version write standard output too: a write error there is exit 74 as well.
  const auto flushed = [&](int rc) {
    std::cout.flush();
    if (!std::cout) {
      std::cerr << prog << ": <stdout>: write error\n";
      return static_cast<int>(ExitCode::io);
    }
    return rc;
  };
  try {
    app.parse(argc, argv);
  } catch (const CLI::CallForHelp& e) {
    return flushed(app.exit(e));  // prints help to stdout, returns 0
  } catch (const CLI::CallForAllHelp& e) {
    return flushed(app.exit(e));
  } catch (const CLI::CallForVersion& e) {
    std::cout << e.what() << "\n";
    return flushed(0);
  } catch (const CLI::ParseError& e) {
    std::cerr << prog << ": " << clip_message(e.what()) << "\n"
              << "Run '" << prog << " --help' for usage.\n";
    return static_cast<int>(ExitCode::usage);
  }
  install_stop_handlers();
  try {
    return flushed(body());
  } catch (const Error& e) {
    std::cerr << prog << ": " << clip_message(e.what()) << "\n";
    return static_cast<int>(e.code());
  } catch (const std::bad_alloc&) {
    std::cerr << prog << ": out of memory\n";
    return static_cast<int>(ExitCode::software);
  } catch (const std::exception& e) {
    std::cerr << prog << ": internal error: " << clip_message(e.what()) << "\n";
    return static_cast<int>(ExitCode::software);
  }
}

unsigned resolve_threads(unsigned requested) { return resolve_thread_count(requested); }

nlohmann::json provenance() {
  if (!g_have_provenance) return nlohmann::json::object();
  return {{"tool", g_tool}, {"version", kVersion}, {"argv", g_argv}};
}

std::string provenance_comment() {
  if (!g_have_provenance) return {};
  std::string s = "# " + g_tool + " " + kVersion + "\n# argv:";
  // A line break inside an argument must not end the comment (the rest would become data, or a
  // gnuplot command in turnfit-plot's script): written as the two characters \n.
  for (const auto& a : g_argv) {
    s += ' ';
    for (char c : a) {
      if (c == '\n') s += "\\n";
      else if (c == '\r') s += "\\r";
      else s += c;
    }
  }
  return s + "\n";
}

void warn(const CommonOptions& opts, const std::string& message) {
  if (!opts.quiet) std::cerr << (g_tool.empty() ? "turnfit" : g_tool) << ": warning: " << clip_message(message) << "\n";
}

bool stderr_is_tty() { return ::isatty(2) == 1; }

std::string fmt(double x, int digits) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.*g", digits, x);
  return buf;
}

}  // namespace turnfit::cli
