// IO layer: CSV and JSON readers reject bad input with file and line; outputs are atomic.
#include <catch2/catch.hpp>
#include <cstdio>
#include <dirent.h>
#include <fstream>
#include <sys/stat.h>
#include <unistd.h>

#include "turnfit/io/csv.hpp"
#include "turnfit/io/error.hpp"
#include "turnfit/io/json.hpp"
#include "turnfit/io/output.hpp"
#include "turnfit/io/text.hpp"

using namespace turnfit;
using Catch::Matchers::Contains;

namespace {
std::string fail_message(const std::function<void()>& f, int expect_code) {
  try {
    f();
  } catch (const Error& e) {
    CHECK(static_cast<int>(e.code()) == expect_code);
    return e.what();
  }
  FAIL("no error thrown");
  return {};
}

std::string temp_dir() {
  char tmpl[] = "/tmp/turnfit-test-XXXXXX";
  REQUIRE(::mkdtemp(tmpl) != nullptr);
  return tmpl;
}

int count_files(const std::string& dir) {
  int n = 0;
  if (DIR* d = ::opendir(dir.c_str())) {
    while (dirent* e = ::readdir(d))
      if (e->d_name[0] != '.') ++n;
    ::closedir(d);
  }
  return n;
}
}  // namespace

TEST_CASE("io: CSV with comments, header and numbers", "[io]") {
  CsvTable t = CsvTable::parse("# probe RRL\nposition_mm,intensity\n1.5,0.2\n\n# mid\n2.0, 3e-1\r\n", "p.csv");
  REQUIRE(t.rows() == 2);
  CHECK(t.number(1, t.column("intensity")) == Approx(0.3));
  CHECK(t.line(1) == 6);
  CHECK(t.comments().size() == 2);
}

TEST_CASE("io: CSV errors name file, line and column", "[io]") {
  CHECK_THAT(fail_message([] { CsvTable::parse("", "e.csv"); }, 65), Contains("e.csv") && Contains("empty"));
  CHECK_THAT(fail_message([] { CsvTable::parse("# only\n\n", "c.csv"); }, 65), Contains("empty"));
  CHECK_THAT(fail_message([] { CsvTable::parse("a,b\n1,2\n3\n", "w.csv"); }, 65), Contains("w.csv:3:"));
  CHECK_THAT(fail_message([] { CsvTable::parse("a,a\n", "d.csv"); }, 65), Contains("duplicate"));
  CsvTable t = CsvTable::parse("a,b\n1,x\n2,nan\n3,inf\n4,\n", "n.csv");
  CHECK_THAT(fail_message([&] { t.number(0, 1); }, 65), Contains("n.csv:2:") && Contains("'b'"));
  CHECK_THAT(fail_message([&] { t.number(1, 1); }, 65), Contains("n.csv:3:"));
  CHECK_THAT(fail_message([&] { t.number(2, 1); }, 65), Contains("n.csv:4:"));
  CHECK_THAT(fail_message([&] { t.number(3, 1); }, 65), Contains("n.csv:5:") && Contains("empty"));
  CHECK_THAT(fail_message([&] { t.require_columns({"a", "c", "d"}); }, 65), Contains("'c', 'd'"));
  CHECK_THAT(fail_message([] { CsvTable::parse(std::string("a\n1\0", 5), "bin"); }, 65), Contains("NUL"));
}

TEST_CASE("io: JSON syntax errors carry the line", "[io]") {
  CHECK(parse_json("{\"a\": 1}", "x.json")["a"] == 1);
  CHECK_THAT(fail_message([] { parse_json("{\n \"a\": 1,\n \"b\": }\n", "bad.json"); }, 65), Contains("bad.json:3:"));
  CHECK_THAT(fail_message([] { parse_json("  \n", "e.json"); }, 65), Contains("empty"));
  CHECK_THAT(fail_message([] { parse_json("{\"a\": [1, 2", "t.json"); }, 65), Contains("t.json:1:"));
}

TEST_CASE("io: strict numbers", "[io]") {
  CHECK(parse_double(" 1.5e3 ", "f", 1, "x") == 1500);
  CHECK_THAT(fail_message([] { parse_double("1.5.3", "f", 7, "x"); }, 65), Contains("f:7:"));
  CHECK_THAT(fail_message([] { parse_double("NaN", "f", 1, "x"); }, 65), Contains("finite"));
  CHECK_THAT(fail_message([] { parse_double("1e999", "f", 1, "x"); }, 65), Contains("finite"));
  CHECK(parse_long("42", "f", 1, "n") == 42);
  CHECK_THAT(fail_message([] { parse_long("4.2", "f", 2, "n"); }, 65), Contains("f:2:"));
  CHECK(split_blanks("  a  b\tc ").size() == 3);
}

TEST_CASE("io: outputs appear only when committed", "[io]") {
  const std::string dir = temp_dir();
  const std::string path = dir + "/out.csv";
  {
    OutputFile out(path);
    out.stream() << "partial";
    CHECK(count_files(dir) == 1);  // the temporary only
    struct stat st {};
    CHECK(::stat(path.c_str(), &st) != 0);
  }  // destroyed without commit: nothing left
  CHECK(count_files(dir) == 0);
  {
    OutputFile out(path);
    out.stream() << "a,b\n1,2\n";
    out.commit();
  }
  CHECK(count_files(dir) == 1);
  std::ifstream f(path);
  std::string first;
  std::getline(f, first);
  CHECK(first == "a,b");
  CHECK_THAT(fail_message([&] { OutputFile o(dir + "/no/such/dir/x.csv"); }, 73), Contains("cannot create"));
  CHECK_THAT(fail_message([] { read_input("/no/such/file.csv"); }, 66), Contains("/no/such/file.csv"));
  std::remove(path.c_str());
  ::rmdir(dir.c_str());
}

TEST_CASE("io: devices are written in place and links are followed", "[io]") {
  {
    OutputFile out("/dev/null");
    out.stream() << "discarded\n";
    out.commit();
  }
  struct stat st {};
  REQUIRE(::stat("/dev/null", &st) == 0);
  CHECK(S_ISCHR(st.st_mode));
  const std::string dir = temp_dir();
  const std::string target = dir + "/target.csv", link = dir + "/link.csv";
  REQUIRE(::symlink("target.csv", link.c_str()) == 0);
  {
    OutputFile out(link);
    out.stream() << "x\n";
    out.commit();
  }
  REQUIRE(::lstat(link.c_str(), &st) == 0);
  CHECK(S_ISLNK(st.st_mode));
  std::ifstream f(target);
  std::string line;
  std::getline(f, line);
  CHECK(line == "x");
  std::remove(link.c_str());
  std::remove(target.c_str());
  ::rmdir(dir.c_str());
}
