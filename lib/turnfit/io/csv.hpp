// CSV tables with a header row, '#' comment lines, and errors that name file and line.
#pragma once

#include <string>
#include <vector>

namespace turnfit {

/// A parsed CSV table: header names, rows of raw cells, and the source line of each row.
class CsvTable {
 public:
  /// Parses text (name is used in messages). The first non-comment, non-blank line is the
  /// header; every later row must have as many fields. Throws EX_DATAERR on an empty
  /// input, a duplicate column or a row of the wrong width.
  static CsvTable parse(const std::string& text, const std::string& name);
  /// Reads and parses a file ("-" for stdin).
  static CsvTable read(const std::string& path);

  /// Column index of name; EX_DATAERR naming the file and the missing column if absent.
  size_t column(const std::string& col) const;
  /// Whether the header has this column.
  bool has_column(const std::string& col) const;
  /// Requires all listed columns (one message listing every missing one).
  void require_columns(const std::vector<std::string>& cols) const;
  /// Number of data rows.
  size_t rows() const { return cells_.size(); }
  /// Raw cell text.
  const std::string& cell(size_t row, size_t col) const { return cells_[row][col]; }
  /// Cell as a finite number, or EX_DATAERR "file:line: column 'c': ...".
  double number(size_t row, size_t col) const;
  /// Source line number (1-based) of a data row.
  long line(size_t row) const { return lines_[row]; }
  /// Header names in order.
  const std::vector<std::string>& header() const { return header_; }
  /// Comment lines ('#' included) in input order.
  const std::vector<std::string>& comments() const { return comments_; }
  /// Name of the input, as used in messages.
  const std::string& name() const { return name_; }

 private:
  std::string name_;
  std::vector<std::string> header_;
  std::vector<std::vector<std::string>> cells_;
  std::vector<long> lines_;
  std::vector<std::string> comments_;
};

}  // namespace turnfit
