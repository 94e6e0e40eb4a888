// Replays inputs through a fuzz target in an ordinary build: the regression inputs under
// tests/fuzz/regressions/<target>/ and the seed corpus, each file once. A bug aborts (fuzz.hpp).
// Beyond that, a regression input must still be refused (each was bad input that a reader once
// took, or crashed on), unless its name starts with "accepted-" (input that broke a later step
// and must now pass); a seed must still be accepted.
#include <algorithm>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <iterator>
#include <string>
#include <vector>

#include "fuzz.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size);

int main(int argc, char** argv) {
  namespace fs = std::filesystem;
  std::vector<fs::path> files;
  for (int i = 1; i < argc; ++i) {
    const fs::path p(argv[i]);
    if (fs::is_directory(p)) {
      for (const auto& e : fs::recursive_directory_iterator(p))
        if (e.is_regular_file() && e.path().filename().string()[0] != '.') files.push_back(e.path());
    } else if (fs::is_regular_file(p)) {
      files.push_back(p);
    } else {
      std::cerr << "replay: " << p.string() << ": no such file or folder\n";
      return 2;
    }
  }
  std::sort(files.begin(), files.end());
  int wrong = 0;
  for (const auto& f : files) {
    std::ifstream in(f, std::ios::binary);
    const std::string data((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    turnfit::fuzz::refused = false;
    LLVMFuzzerTestOneInput(reinterpret_cast<const std::uint8_t*>(data.data()), data.size());
    const bool regression = f.string().find("/regressions/") != std::string::npos;
    const bool must_refuse = regression && f.filename().string().rfind("accepted-", 0) != 0;
    const bool ok = turnfit::fuzz::refused == must_refuse;
    wrong += !ok;
    std::cerr << "replay: " << f.string() << " (" << data.size() << " bytes): "
              << (turnfit::fuzz::refused ? "refused" : "accepted") << (ok ? "" : ", WRONG: it must be ")
              << (ok ? "" : must_refuse ? "refused" : "accepted") << "\n";
  }
  std::cout << "replay: " << files.size() << " inputs, no bug, " << wrong << " with the wrong outcome\n";
  return files.empty() || wrong ? 1 : 0;
}
