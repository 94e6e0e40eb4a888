// CSV reading: strict, so that a truncated or garbled table is an error, not a wrong number.
#include "turnfit/io/csv.hpp"

#include <algorithm>

#include "turnfit/io/error.hpp"
#include "turnfit/io/limits.hpp"
#include "turnfit/io/text.hpp"

namespace turnfit {

CsvTable CsvTable::parse(const std::string& text, const std::string& name) {
  CsvTable t;
  t.name_ = name;
  if (text.find('\0') != std::string::npos)
    throw data_error(name, 0, "binary data (NUL byte) where CSV text is expected");
  auto lines = split_lines(text, name);
  bool have_header = false;
  for (size_t i = 0; i < lines.size(); ++i) {
    std::string_view l = trim(lines[i]);
    long lineno = static_cast<long>(i + 1);
    if (l.empty()) continue;
    if (l.front() == '#') {
      t.comments_.emplace_back(l);
      continue;
    }
    auto fields = split_fields(l, ',');
    if (!have_header) {
      for (auto f : fields) {
        if (f.empty()) throw data_error(name, lineno, "empty column name in header");
        std::string s(f);
        if (std::find(t.header_.begin(), t.header_.end(), s) != t.header_.end())
          throw data_error(name, lineno, "duplicate column '" + s + "' in header");
        t.header_.push_back(s);
      }
      have_header = true;
      continue;
    }
    if (fields.size() != t.header_.size())
      throw data_error(name, lineno,
                       "expected " + std::to_string(t.header_.size()) + " fields (" +
                           std::to_string(t.header_.size()) + " columns in the header), found " +
                           std::to_string(fields.size()));
    if (t.cells_.size() >= limits::kTableRows)
      throw data_error(name, lineno, "more than " + std::to_string(limits::kTableRows) +
                                         " data rows: refused (the limit of one table)");
    std::vector<std::string> row;
    row.reserve(fields.size());
    for (auto f : fields) row.emplace_back(f);
    t.cells_.push_back(std::move(row));
    t.lines_.push_back(lineno);
  }
  if (!have_header) throw data_error(name, 0, "empty input: no CSV header found");
  return t;
}

CsvTable CsvTable::read(const std::string& path) {
  InputText in = read_input(path);
  return parse(in.text, in.name);
}

bool CsvTable::has_column(const std::string& col) const {
  return std::find(header_.begin(), header_.end(), col) != header_.end();
}

size_t CsvTable::column(const std::string& col) const {
  auto it = std::find(header_.begin(), header_.end(), col);
  if (it == header_.end()) throw data_error(name_, 0, "missing column '" + col + "'");
  return static_cast<size_t>(it - header_.begin());
}

void CsvTable::require_columns(const std::vector<std::string>& cols) const {
  std::string missing;
  for (const auto& c : cols)
    if (!has_column(c)) missing += (missing.empty() ? "'" : ", '") + c + "'";
  if (!missing.empty()) {
    std::string have;
    for (const auto& h : header_) have += (have.empty() ? "" : ",") + h;
    throw data_error(name_, 0, "missing column(s) " + missing + " (header is: " + have + ")");
  }
}

double CsvTable::number(size_t row, size_t col) const {
  return parse_double(cells_[row][col], name_, lines_[row], "column '" + header_[col] + "'");
}

}  // namespace turnfit
