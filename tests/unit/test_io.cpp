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
#include "turnfit/io/limits.hpp"
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
  // Only decimals (issue 18: hex floats passed strtod in maps).
  for (const char* bad : {"0x1p3", "0X10", "inf", "-Infinity", "nan(1)", "1e", "e5", ".", "+", "1.5f", "1,5", " 1"})
    CHECK_FALSE(is_decimal(bad));
  for (const char* good : {"1", "-1.", ".5", "+2.5e-3", "1E+300", "007"}) CHECK(is_decimal(good));
  double v = 0;
  CHECK_FALSE(parse_decimal("1e400", v));
  CHECK((parse_decimal("-2.5e-3", v) && v == -2.5e-3));
  CHECK_THAT(fail_message([] { parse_double("0x1p3", "f", 3, "x"); }, 65), Contains("f:3: x: '0x1p3' is not a number"));
  CHECK_THAT(fail_message([] { parse_long("99999999999999999999", "f", 2, "n"); }, 65), Contains("not an integer"));
  CHECK_THAT(fail_message([] { parse_long("+-1", "f", 2, "n"); }, 65), Contains("not an integer"));
}

TEST_CASE("io: hostile JSON is refused with the line and the limit (issue 18)", "[io]") {
  // Nesting: the limit itself parses, one more level does not (copies of 150k levels crashed).
  const auto nested = [](int depth) { return std::string(depth, '[') + std::string(depth, ']'); };
  CHECK(parse_json(nested(limits::kJsonDepth), "f").is_array());
  CHECK_THAT(fail_message([&] { parse_json("\n" + nested(limits::kJsonDepth + 1), "f"); }, 65),
             Contains("f:2: invalid JSON: nested deeper than 64 levels"));
  // Brackets inside strings, escaped quotes included, do not nest.
  CHECK(parse_json("[\"" + std::string(100, '[') + "\\\"" + std::string(100, '{') + "\"]", "f").size() == 1);
  // A NUL ends nlohmann's input: the garbage behind it must not pass.
  CHECK_THAT(fail_message([] { parse_json(std::string("{}\n\0garbage", 12), "f"); }, 65), Contains("f:2: invalid JSON: a NUL byte"));
  CHECK_THAT(fail_message([] { parse_json("{\"a\": 1,\n \"b\": -1e400}", "f"); }, 65),
             Contains("f:2: invalid JSON: number overflow parsing '-1e400'"));
  CHECK_THAT(fail_message([] { parse_json("{} x", "f"); }, 65), Contains("f:1: invalid JSON: syntax error"));
  // Writing never throws on bytes that are not UTF-8.
  nlohmann::json j = {{"name", std::string("TC\xff" "1")}};
  CHECK(json_text(j) == "{\"name\":\"TC\xef\xbf\xbd" "1\"}");
}

TEST_CASE("io: quoted text and messages stay short and printable (issue 18)", "[io]") {
  CHECK(quote("abc") == "'abc'");
  const std::string big(10 << 20, '7');
  CHECK(quote(big) == "'" + std::string(limits::kEcho, '7') + "'... (10485760 bytes)");
  CHECK(quote("a\x1b[31mb\xff") == "'a\\x1B[31mb\\xFF'");  // a terminal escape and a bad byte
  CHECK(quote("\xc3\xa9t\xc3\xa9") == "'\xc3\xa9t\xc3\xa9'");    // UTF-8 passes
  // A cut never splits a character: 59 ASCII bytes and a two-byte one straddling the limit.
  CHECK(quote(std::string(59, 'a') + "\xc3\xa9xyz") == "'" + std::string(59, 'a') + "'... (64 bytes)");
  const std::string msg = clip_message("f:1: x: '" + big + "' is not a number\nsecond line\tand a tab");
  CHECK(msg.size() < limits::kMessageBytes + 100);
  CHECK_THAT(msg, Contains("f:1: x: '777") && Contains("bytes left out") && Contains("second line\tand a tab"));
  CHECK(clip_message("two\nlines") == "two\nlines");
  CHECK(clip_message("bell\a") == "bell\\x07");
}

TEST_CASE("io: bounded inputs (issue 18)", "[io]") {
  const std::string dir = temp_dir();
  const std::string path = dir + "/big.txt";
  std::ofstream(path) << std::string(1000, 'x');
  CHECK(read_input(path, 1000).text.size() == 1000);
  CHECK_THAT(fail_message([&] { read_input(path, 999); }, 65), Contains("big.txt: file of 0 MiB: larger than the 0 MiB"));
  std::string text = "a\n" + std::string(limits::kLineBytes + 1, 'y') + "\nb";
  CHECK_THAT(fail_message([&] { split_lines(text, "t"); }, 65), Contains("t:2: line of 1048577 bytes"));
  CHECK(split_lines("a\nb", "t").size() == 2);
  std::remove(path.c_str());
  rmdir(dir.c_str());
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
