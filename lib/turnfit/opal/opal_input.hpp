// The part of OPAL's input language that cyclotron inputs use: statements, variables with
// arithmetic expressions, IF blocks, element commands and LINEs, read into a form the importer
// can query attribute by attribute.
#pragma once

#include <map>
#include <memory>
#include <string>
#include <vector>

namespace turnfit::opal {

/// One token of an OPAL input, with the line it starts on.
struct Token {
  enum class Kind { name, number, string, punct };
  Kind kind = Kind::punct;
  std::string text;  ///< as written (a string without its quotes)
  long line = 0;
};

/// `NAME = value` of a command; the value is kept as tokens and evaluated on demand, as the
/// importer knows which type each attribute has.
struct Attribute {
  std::string name;            ///< upper case
  std::string spelled;         ///< as written
  std::vector<Token> value;    ///< empty for a bare flag (`OPTION, ECHO;`)
  long line = 0;
  long seq = 0;                ///< where its value is evaluated (`:=`: after the whole input)
};

/// One command: `[label:] KEYWORD, attr = value, ...;` or `label: LINE = (a, b, ...);`.
struct Command {
  long line = 0;
  long seq = 0;                      ///< statement number (definitions before it are in force)
  std::string label;                 ///< as written ("" when none)
  std::string keyword;               ///< upper case: CYCLOTRON, RFCAVITY, OPTION, ...
  std::string keyword_spelled;       ///< as written
  std::vector<Attribute> attrs;
  std::vector<Token> line_members;   ///< LINE only: the element names in order
  /// The attribute NAME (upper case), or nullptr.
  const Attribute* find(const std::string& name) const;
};

/// A remark about the input for the user: what was read but not used, and why.
struct Note {
  long line = 0;
  std::string text;
  bool explained = true;  ///< false: the importer does not understand it (an error with --strict)
};

/// OPAL's version number as OPALVERSION gives it: major * 10000 + minor * 100 + patch
/// (2022.1.0 is 20220100). Parses "2022.1", "2022.1.0", "2.0" or the number itself;
/// EX_USAGE otherwise.
double parse_opal_version(const std::string& text);

/// A parsed input: commands in order (IF branches already chosen), variables and notes.
/// As in OPAL, `x = e` is evaluated where it stands and `x := e` where x is used (with the
/// whole input's definitions), so a circular definition is found when first needed. Every error is EX_DATAERR
/// "file:line: ... 'token' ...".
class Input {
 public:
  /// Parses text (`name` is used in messages) for OPAL version `opal_version` (OPALVERSION).
  Input(const std::string& text, const std::string& name, double opal_version);
  ~Input();
  Input(Input&&) noexcept;
  Input& operator=(Input&&) noexcept;

  /// The commands, in input order.
  const std::vector<Command>& commands() const;
  /// Remarks made while parsing (ignored OPTIONs, VALUE results, branches taken, ...).
  const std::vector<Note>& notes() const;
  /// The name used in messages.
  const std::string& name() const;

  /// A number: an arithmetic expression.
  double number(const Attribute& a) const;
  /// A string: a quoted string, a STRING variable, or a bare word upper-cased (as OPAL reads it).
  std::string string(const Attribute& a) const;
  /// A boolean: TRUE/FALSE or a logical expression; a bare flag is TRUE.
  bool boolean(const Attribute& a) const;
  /// An array of numbers: `{e1, e2, ...}` or a single expression.
  std::vector<double> numbers(const Attribute& a) const;
  /// A list of names: `{a, b}`, `(a, b)`, a bare name or a quoted one.
  std::vector<std::string> names(const Attribute& a) const;
  /// The value of variable NAME (any case), evaluating it now; EX_DATAERR if undefined.
  double variable(const std::string& name, long line) const;
  /// Where `:=` values are taken: the definitions before statement `seq` (a RUN: OPAL
  /// evaluates deferred expressions when it runs); by default after the whole input.
  void set_evaluation_point(long seq);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

/// Upper-cases an OPAL name (OPAL's names are case-insensitive).
std::string upper(std::string s);

/// Whether an upper-case word has a meaning of its own in the language (a declaration, IF and
/// its kin, a command the importer reads, TRUE/FALSE, a predefined constant): not a label to
/// write.
bool reserved(const std::string& up);

}  // namespace turnfit::opal
