// The fuzz targets' shared helpers.
#include "fuzz.hpp"

#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>

namespace turnfit::fuzz {

void bug(const std::string& what) {
  std::cerr << "turnfit fuzz: BUG: " << what << std::endl;
  std::abort();
}

const std::string& work_dir() {
  // Never destroyed: the exit handler that removes the folder runs after static destructors.
  static const std::string* dir = [] {
    auto* tmpl = new std::string((std::filesystem::temp_directory_path() / "turnfit-fuzz-XXXXXX").string());
    if (!::mkdtemp(tmpl->data())) bug("cannot make a temporary folder");
    std::atexit([] {
      std::error_code ec;
      std::filesystem::remove_all(work_dir(), ec);
    });
    return tmpl;
  }();
  return *dir;
}

std::string as_file(const std::uint8_t* data, std::size_t size, const std::string& name) {
  const std::string path = work_dir() + "/" + name;
  std::ofstream f(path, std::ios::binary | std::ios::trunc);
  f.write(reinterpret_cast<const char*>(data), static_cast<std::streamsize>(size));
  if (!f) bug("cannot write " + path);
  return path;
}

std::string ring8_dir() { return std::string(TURNFIT_SOURCE_SHARE) + "/ring8"; }

}  // namespace turnfit::fuzz
