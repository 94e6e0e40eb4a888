// OPAL input language: tokens, statements, IF blocks and lazily evaluated expressions.
#include "turnfit/opal/opal_input.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <functional>
#include <limits>
#include <set>

#include "turnfit/io/error.hpp"
#include "turnfit/io/limits.hpp"
#include "turnfit/io/text.hpp"

namespace turnfit::opal {

std::string upper(std::string s) {
  for (char& c : s) c = static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
  return s;
}

const Attribute* Command::find(const std::string& n) const {
  for (const auto& a : attrs)
    if (a.name == n) return &a;
  return nullptr;
}

double parse_opal_version(const std::string& text) {
  // "2022.1" style: parts major.minor[.patch]; a plain integer is the OPALVERSION number.
  std::vector<long> parts;
  std::string cur;
  for (size_t i = 0; i <= text.size(); ++i) {
    if (i == text.size() || text[i] == '.') {
      if (cur.empty() || cur.size() > 8) throw usage_error("--opal-version: '" + text + "' is not a version (e.g. 2022.1)");
      parts.push_back(std::stol(cur));
      cur.clear();
    } else if (std::isdigit(static_cast<unsigned char>(text[i]))) {
      cur += text[i];
    } else {
      throw usage_error("--opal-version: '" + text + "' is not a version (e.g. 2022.1)");
    }
  }
  if (parts.size() == 1 && parts[0] >= 10000) return static_cast<double>(parts[0]);
  if (parts.size() < 2 || parts.size() > 3 || parts[1] > 99 || (parts.size() == 3 && parts[2] > 99))
    throw usage_error("--opal-version: '" + text + "' is not a version (e.g. 2022.1)");
  return static_cast<double>(parts[0] * 10000 + parts[1] * 100 + (parts.size() == 3 ? parts[2] : 0));
}

namespace {

using Kind = Token::Kind;
using Tokens = std::vector<Token>;

// OPAL's predefined constants (its RealConstant.cpp and Physics.h, CODATA 2018; masses in GeV,
// as OPAL's inputs use them). ALPHAMASS is CODATA's alpha mass (not found in OPAL's source).
constexpr double kAmu = 0.93149410242;
const std::map<std::string, double>& constants() {
  static const std::map<std::string, double> k = {
      {"PI", M_PI},
      {"TWOPI", 2 * M_PI},
      {"RADDEG", 180 / M_PI},
      {"DEGRAD", M_PI / 180},
      {"E", std::exp(1.0)},
      {"EMASS", 0.51099895e-3},
      {"PMASS", 0.93827208816},
      {"MUMASS", 0.1056583755},
      {"HMMASS", 1.00837 * kAmu},
      {"H2PMASS", 2.01510 * kAmu},
      {"DMASS", 2.013553212745 * kAmu},
      {"ALPHAMASS", 3.7273794066},
      {"CMASS", 12 * kAmu},
      {"XEMASS", 124 * kAmu},
      {"UMASS", 238.050787 * kAmu},
      {"AMU", kAmu},
      {"CLIGHT", 299792458.0},
      {"RANK", 0.0},
  };
  return k;
}

bool is_name_start(char c) { return std::isalpha(static_cast<unsigned char>(c)) || c == '_'; }
bool is_name_char(char c) {
  return std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '.' || c == '\'';
}

std::string show(const Token& t) {
  if (t.kind == Kind::string) return quote("\"" + t.text + "\"");
  return quote(t.text);
}

// One definition of a variable. As in OPAL, `x = e` is evaluated where it stands (`value`),
// `x := e` wherever x is used (its expression, with the definitions in force there).
struct Definition {
  std::string spelled;
  std::string type;  // REAL, BOOL or STRING
  Tokens expr;
  long line = 0;
  long seq = 0;      // statement number: what comes later does not see it
  bool is_const = false;
  bool deferred = false;
  double value = 0;  // immediate definitions
};
constexpr long kEnd = std::numeric_limits<long>::max();  // "after the whole input": deferred values
constexpr size_t kAttributes = 10000;  // attributes of one command (OPAL's have a few dozen)
constexpr size_t kTokens = 2000000;    // tokens of one input (cyclotron2.in has 700)
// Nested sub-expressions and deferred definitions, together (a definition costs 3: about 2 kB of
// stack each, so 6 MB at most), and tokens evaluated in all (cyclotron2.in: 300; a deferred
// definition is evaluated again wherever the definitions it sees differ; a million take 0.4 s,
// and a few seconds under the sanitizers, within the fuzzers' 10 s timeout).
constexpr int kNesting = 3000;
constexpr long kSteps = 1000000;

// The first ',' outside brackets in t[from, end), or end.
size_t top_level_comma(const Tokens& t, size_t from, size_t end) {
  int depth = 0;
  for (size_t k = from; k < end; ++k) {
    if (t[k].kind != Kind::punct) continue;
    const std::string& p = t[k].text;
    if (p == "," && depth == 0) return k;
    if (p == "(" || p == "{" || p == "[") ++depth;
    if (p == ")" || p == "}" || p == "]") --depth;
  }
  return end;
}

bool is_decl(const std::string& up) {
  return up == "REAL" || up == "CONST" || up == "CONSTANT" || up == "BOOL" || up == "STRING" || up == "INTEGER" ||
         up == "VECTOR";
}

}  // namespace

bool reserved(const std::string& up) {
  static const std::set<std::string> words = {
      "IF", "ELSE", "WHILE", "MACRO", "TRUE", "FALSE", "OPALVERSION", "LINE", "OPTION", "TITLE", "VALUE",
      "SELECT", "TRACK", "RUN", "ENDTRACK", "STOP", "QUIT", "ECHO", "CYCLOTRON", "RFCAVITY", "TRIMCOIL",
      "PROBE", "BEAM", "DISTRIBUTION", "FIELDSOLVER"};
  return is_decl(up) || words.count(up) > 0 || constants().count(up) > 0;
}

struct Input::Impl {
  std::string name;
  double version = 0;
  Tokens toks;
  size_t pos = 0;
  std::vector<Command> commands;
  std::vector<Note> notes;
  std::map<std::string, std::vector<Definition>> vars;  // each name's definitions in input order
  long seq = 0;                                          // statements read so far
  mutable std::vector<std::string> evaluating;           // for circular definitions
  mutable int nesting = 0;                               // Nest: the evaluation's depth
  mutable long steps = 0;                                // tokens evaluated (kSteps)
  mutable std::map<std::pair<const Definition*, long>, double> memo;  // deferred values by context
  long run_at = kEnd;                                    // where ':=' values are taken (set_evaluation_point)
  bool stopped = false;                                  // STOP or QUIT read: nothing after it is

  // One level of nested evaluation; refused past kNesting (the stack is finite).
  struct Nest {
    const Impl& in;
    Nest(const Impl& i, long line) : in(i) {
      if (in.nesting >= kNesting) throw in.error(line, "expression or definitions nested too deeply");
      ++in.nesting;
    }
    ~Nest() { --in.nesting; }
    Nest(const Nest&) = delete;
    Nest& operator=(const Nest&) = delete;
  };

  // Where an attribute's value is taken: where it stands, or for ':=' at the evaluation point.
  long when(const Attribute& a) const { return a.seq == kEnd ? run_at : a.seq; }

  // The definition of `key` in force at statement `at`, or nullptr.
  const Definition* definition(const std::string& key, long at) const {
    auto it = vars.find(key);
    if (it == vars.end()) return nullptr;
    // Definitions are kept in input order: the last one before `at`.
    const auto& defs = it->second;
    auto k = std::lower_bound(defs.begin(), defs.end(), at, [](const Definition& x, long a) { return x.seq < a; });
    return k == defs.begin() ? nullptr : &*std::prev(k);
  }

  Error error(long line, const std::string& msg) const { return data_error(name, line, msg); }

  // ---- tokens ----
  // Moves i past blanks and comments (counting lines); an unclosed '/*' is an error.
  void skip_blanks(const std::string& text, size_t& i, long& line) const {
    const size_t n = text.size();
    while (i < n) {
      const char c = text[i];
      if (c == '\n') {
        ++line;
        ++i;
      } else if (c == ' ' || c == '\t' || c == '\r' || c == '\f' || c == '\v') {
        ++i;
      } else if (c == '/' && i + 1 < n && text[i + 1] == '/') {
        while (i < n && text[i] != '\n') ++i;
      } else if (c == '/' && i + 1 < n && text[i + 1] == '*') {
        const long start = line;
        i += 2;
        while (i + 1 < n && !(text[i] == '*' && text[i + 1] == '/')) {
          if (text[i] == '\n') ++line;
          ++i;
        }
        if (i + 1 >= n) throw error(start, "'/*' comment is never closed");
        i += 2;
      } else {
        return;
      }
    }
  }

  void lex(const std::string& text) {
    long line = 1;
    size_t i = 0;
    int braces = 0;           // IF blocks (and arrays) open here
    bool at_statement = true;  // the next token starts a statement
    const size_t n = text.size();
    for (;;) {
      skip_blanks(text, i, line);
      if (i >= n) break;
      const char c = text[i];
      if (toks.size() >= kTokens) throw error(line, "more than " + std::to_string(kTokens) + " tokens");
      Token t;
      t.line = line;
      if (is_name_start(c)) {
        size_t j = i;
        while (j < n && is_name_char(text[j])) ++j;
        t.kind = Kind::name;
        t.text = text.substr(i, j - i);
        i = j;
      } else if (std::isdigit(static_cast<unsigned char>(c)) ||
                 (c == '.' && i + 1 < n && std::isdigit(static_cast<unsigned char>(text[i + 1])))) {
        size_t j = i;
        while (j < n && std::isdigit(static_cast<unsigned char>(text[j]))) ++j;
        if (j < n && text[j] == '.') {
          ++j;
          while (j < n && std::isdigit(static_cast<unsigned char>(text[j]))) ++j;
        }
        if (j < n && (text[j] == 'e' || text[j] == 'E')) {
          size_t k = j + 1;
          if (k < n && (text[k] == '+' || text[k] == '-')) ++k;
          if (k < n && std::isdigit(static_cast<unsigned char>(text[k]))) {
            while (k < n && std::isdigit(static_cast<unsigned char>(text[k]))) ++k;
            j = k;
          }
        }
        t.kind = Kind::number;
        t.text = text.substr(i, j - i);
        if (j < n && is_name_start(text[j])) {
          size_t k = j;
          while (k < n && is_name_char(text[k])) ++k;
          throw error(line, "'" + text.substr(i, k - i) + "' is neither a number nor a name");
        }
        i = j;
      } else if (c == '"' || c == '\'') {
        size_t j = i + 1;
        while (j < n && text[j] != c && text[j] != '\n') ++j;
        if (j >= n || text[j] != c) throw error(line, "string " + quote(text.substr(i, j - i)) + " is never closed");
        t.kind = Kind::string;
        t.text = text.substr(i + 1, j - i - 1);
        i = j + 1;
      } else {
        static const char* const two[] = {":=", "<=", ">=", "==", "!=", "&&", "||"};
        t.kind = Kind::punct;
        bool done = false;
        for (const char* p : two)
          if (i + 1 < n && c == p[0] && text[i + 1] == p[1]) {
            t.text = p;
            i += 2;
            done = true;
            break;
          }
        if (!done) {
          if (std::string(",;:=(){}[]+-*/^<>!").find(c) == std::string::npos)
            throw error(line, "unexpected character " + quote(std::string(1, c)));
          t.text = std::string(1, c);
          ++i;
        }
      }
      const bool stop = at_statement && braces == 0 && t.kind == Kind::name &&
                        (upper(t.text) == "STOP" || upper(t.text) == "QUIT");
      if (t.kind == Kind::punct && t.text == "{") ++braces;
      if (t.kind == Kind::punct && t.text == "}") --braces;
      at_statement = t.kind == Kind::punct && (t.text == ";" || t.text == "}" || t.text == "{");
      toks.push_back(std::move(t));
      if (stop) {
        // OPAL reads no further than a STOP at the top level: whatever follows is not lexed
        // (an unclosed string there is no error), only counted for the note.
        size_t j = i;
        long semicolon_line = line;
        skip_blanks(text, j, semicolon_line);  // blanks and comments before its ';'
        if (j < n && text[j] == ';') {
          line = semicolon_line;
          toks.push_back(Token{Kind::punct, ";", line});
          // Lines after the STOP's that hold anything, for the note.
          bool content = false;
          for (size_t k = text.find('\n', j); k < n; ++k) {
            if (text[k] == '\n') {
              unread_ += content;
              content = false;
            } else if (!std::isspace(static_cast<unsigned char>(text[k]))) {
              content = true;
            }
          }
          unread_ += content;
          return;
        }
      }
    }
  }
  long unread_ = 0;  // lines with text after a top-level STOP

  // ---- statements ----
  bool at_end() const { return pos >= toks.size(); }
  const Token& peek(size_t k = 0) const { return toks[pos + k]; }
  bool peek_is(const std::string& p, size_t k = 0) const {
    return pos + k < toks.size() && toks[pos + k].kind == Kind::punct && toks[pos + k].text == p;
  }
  bool peek_name(const std::string& up, size_t k = 0) const {
    return pos + k < toks.size() && toks[pos + k].kind == Kind::name && upper(toks[pos + k].text) == up;
  }
  long last_line() const { return toks.empty() ? 1 : toks.back().line; }

  // The tokens of one statement: up to ';' at bracket depth 0 (or a '}' closing the block).
  Tokens statement_tokens() {
    Tokens out;
    int depth = 0;
    const long start = peek().line;
    while (!at_end()) {
      const Token& t = peek();
      if (t.kind == Kind::punct) {
        if (t.text == ";" && depth == 0) {
          ++pos;
          return out;
        }
        if (t.text == "}" && depth == 0) return out;  // block ends without ';'
        if (t.text == "(" || t.text == "{" || t.text == "[") ++depth;
        if (t.text == ")" || t.text == "}" || t.text == "]") {
          if (--depth < 0) throw error(t.line, "unbalanced " + show(t));
        }
      }
      out.push_back(t);
      ++pos;
    }
    if (depth != 0) throw error(start, "unbalanced brackets in the statement starting here");
    throw error(start, "statement starting here has no ';'");
  }

  void parse_block(bool take, int depth) {
    if (depth > limits::kJsonDepth) throw error(at_end() ? last_line() : peek().line, "IF blocks nested too deeply");
    while (!at_end()) {
      if (peek_is("}")) return;
      if (peek_is(";")) {
        ++pos;
        continue;
      }
      if (peek_name("IF")) {
        parse_if(take, depth);
        if (stopped) return;
        continue;
      }
      if (peek_name("WHILE") || peek_name("MACRO")) {
        const Token t = peek();
        throw error(t.line, show(t) + ": loops and macros are not read by turnfit-import-opal");
      }
      if (peek_name("ELSE")) throw error(peek().line, "'ELSE' without an IF");
      Tokens st = statement_tokens();
      if (take && !st.empty()) statement(st);
      if (stopped) return;
    }
  }

  void expect(const std::string& p, const std::string& what) {
    if (at_end()) throw error(last_line(), "expected " + quote(p) + " " + what + ", found the end of the input");
    if (!peek_is(p)) throw error(peek().line, "expected " + quote(p) + " " + what + ", found " + show(peek()));
    ++pos;
  }

  void parse_if(bool take, int depth) {
    const Token kw = peek();
    ++pos;
    expect("(", "after IF");
    Tokens cond;
    int d = 1;
    while (!at_end()) {
      const Token& t = peek();
      if (t.kind == Kind::punct && t.text == "(") ++d;
      if (t.kind == Kind::punct && t.text == ")" && --d == 0) break;
      cond.push_back(t);
      ++pos;
    }
    expect(")", "closing the IF condition");
    bool value = false;
    if (take) {
      if (cond.empty()) throw error(kw.line, "IF without a condition");
      value = eval_bool_tokens(cond, kw.line, ++seq);
      notes.push_back({kw.line, "IF condition is " + std::string(value ? "true" : "false") + " for OPALVERSION " +
                                    format_exact(version) + ": " + (value ? "its block" : "its ELSE") + " is read",
                       true});
    }
    expect("{", "opening the IF block");
    parse_block(take && value, depth + 1);
    if (stopped) return;
    expect("}", "closing the IF block");
    if (peek_name("ELSE")) {
      ++pos;
      if (peek_name("IF")) {
        parse_if(take && !value, depth + 1);
        return;
      }
      expect("{", "opening the ELSE block");
      parse_block(take && !value, depth + 1);
      if (stopped) return;
      expect("}", "closing the ELSE block");
    }
  }

  void define(const Token& nm, const std::string& type, bool is_const, bool deferred, Tokens expr) {
    if (nm.kind != Kind::name) throw error(nm.line, show(nm) + " is not a variable name");
    const std::string key = upper(nm.text);
    if (constants().count(key) || key == "OPALVERSION")
      throw error(nm.line, show(nm) + " is one of OPAL's constants and cannot be redefined");
    if (expr.empty()) throw error(nm.line, "variable " + show(nm) + " has no value");
    const long at = ++seq;
    if (const Definition* old = definition(key, at)) {
      if (old->is_const)
        throw error(nm.line, "constant " + show(nm) + " was defined on line " + std::to_string(old->line) +
                                 " and cannot be redefined");
      notes.push_back({nm.line, "variable " + nm.text + " redefined (first defined on line " +
                                    std::to_string(old->line) + ")", true});
    }
    Definition d;
    d.spelled = nm.text;
    d.type = type;
    d.line = nm.line;
    d.seq = at;
    d.is_const = is_const;
    d.deferred = deferred;
    if (!deferred && type != "STRING") {
      if (type == "BOOL")
        d.value = eval_bool_tokens(expr, nm.line, at) ? 1 : 0;
      else
        d.value = eval_tokens(expr, nm.line, at);
    }
    if (type == "STRING" && !(expr.size() == 1 && expr[0].kind == Kind::string))
      throw error(nm.line, "string variable " + show(nm) + " must be one quoted string");
    d.expr = std::move(expr);
    vars[key].push_back(std::move(d));
  }

  void statement(const Tokens& st) {
    const Token& first = st[0];
    if (first.kind != Kind::name) throw error(first.line, "a statement cannot start with " + show(first));
    const std::string up = upper(first.text);
    // Declarations: [REAL|BOOL|STRING] [CONST] name (= | :=) expr.
    if (is_decl(up)) {
      size_t k = 0;
      std::string type = "REAL";
      bool is_const = false;
      while (k < st.size() && st[k].kind == Kind::name && is_decl(upper(st[k].text)) && k + 1 < st.size() &&
             st[k + 1].kind == Kind::name) {
        const std::string w = upper(st[k].text);
        if (w == "CONST" || w == "CONSTANT")
          is_const = true;
        else if (w == "VECTOR")
          throw error(st[k].line, show(st[k]) + ": VECTOR variables are not read by turnfit-import-opal");
        else
          type = w == "INTEGER" ? "REAL" : w;
        ++k;
      }
      if (k >= st.size() || st[k].kind != Kind::name || is_decl(upper(st[k].text)))
        throw error(first.line, show(first) + " needs a variable name");
      const Token& nm = st[k];
      if (k + 1 >= st.size() || st[k + 1].kind != Kind::punct || (st[k + 1].text != "=" && st[k + 1].text != ":="))
        throw error(nm.line, "expected '=' after " + show(nm));
      define(nm, type, is_const, st[k + 1].text == ":=", Tokens(st.begin() + static_cast<long>(k) + 2, st.end()));
      return;
    }
    // Plain assignment: a new value for an existing variable (OPAL wants REAL for a new one).
    if (st.size() >= 2 && st[1].kind == Kind::punct && (st[1].text == "=" || st[1].text == ":=")) {
      const Definition* old = definition(up, kEnd);
      if (!old) throw error(first.line, show(first) + " is not defined before: a new variable needs REAL (REAL " + first.text + " = ...)");
      define(first, old->type, false, st[1].text == ":=", Tokens(st.begin() + 2, st.end()));
      return;
    }
    Command c;
    c.line = first.line;
    c.seq = ++seq;
    size_t k = 0;
    if (st.size() >= 2 && st[1].kind == Kind::punct && st[1].text == ":") {
      c.label = first.text;
      k = 2;
      if (k >= st.size() || st[k].kind != Kind::name)
        throw error(first.line, "label " + show(first) + " needs a command after ':'");
    }
    c.keyword_spelled = st[k].text;
    c.keyword = upper(st[k].text);
    ++k;
    if (c.keyword == "STOP" || c.keyword == "QUIT") {
      // OPAL stops reading here: what follows is never parsed or evaluated.
      stopped = true;
      const long rest = unread_;
      if (rest > 0)
        notes.push_back({c.line, c.keyword_spelled + ": OPAL reads no further (" + std::to_string(rest) +
                                     " more line" + (rest == 1 ? "" : "s") + " not read)", true});
    }
    if (c.keyword == "LINE") {
      if (k >= st.size() || st[k].kind != Kind::punct || (st[k].text != "=" && st[k].text != ":="))
        throw error(st[k - 1].line, "expected '= (' after LINE");
      ++k;
      if (k >= st.size() || st[k].text != "(" || st.back().text != ")")
        throw error(st[k - 1].line, "a LINE is a list in parentheses: L1: LINE = (a, b, ...)");
      for (size_t i = k + 1; i + 1 < st.size(); ++i) {
        if (st[i].kind == Kind::name)
          c.line_members.push_back(st[i]);
        else if (!(st[i].kind == Kind::punct && st[i].text == ","))
          throw error(st[i].line, "unexpected " + show(st[i]) + " in a LINE (element names, separated by ',')");
      }
      if (c.label.empty()) throw error(c.line, "a LINE needs a label");
      commands.push_back(std::move(c));
      return;
    }
    std::set<std::string> names;
    while (k < st.size()) {
      if (!(st[k].kind == Kind::punct && st[k].text == ","))
        throw error(st[k].line, "expected ',' before " + show(st[k]));
      ++k;
      if (k >= st.size()) throw error(st[k - 1].line, "an attribute name must follow ','");
      if (st[k].kind != Kind::name) throw error(st[k].line, "expected an attribute name, found " + show(st[k]));
      Attribute a;
      a.spelled = st[k].text;
      a.name = upper(st[k].text);
      a.line = st[k].line;
      a.seq = c.seq;
      ++k;
      if (k < st.size() && st[k].kind == Kind::punct && (st[k].text == "=" || st[k].text == ":=")) {
        if (st[k].text == ":=") a.seq = kEnd;
        ++k;
        const size_t end = top_level_comma(st, k, st.size());
        a.value.assign(st.begin() + static_cast<long>(k), st.begin() + static_cast<long>(end));
        k = end;
        if (a.value.empty()) throw error(a.line, "attribute " + show(st[k - 1]) + " has no value after '='");
      }
      if (!names.insert(a.name).second) throw error(a.line, "attribute " + quote(a.spelled) + " is given twice");
      if (c.attrs.size() >= kAttributes)
        throw error(a.line, "more than " + std::to_string(kAttributes) + " attributes in one command");
      c.attrs.push_back(std::move(a));
    }
    commands.push_back(std::move(c));
  }

  // ---- expressions ----
  struct Parser {
    const Impl& in;
    const Tokens& t;
    long at;  // the statement whose definitions are in force
    size_t i = 0;
    long line;

    bool punct(const std::string& p) const {
      return i < t.size() && t[i].kind == Kind::punct && t[i].text == p;
    }
    Error bad(const std::string& msg) const {
      return in.error(i < t.size() ? t[i].line : line, msg);
    }
    [[noreturn]] void unexpected(const std::string& what) const {
      if (i >= t.size()) throw in.error(t.empty() ? line : t.back().line, "expression ends early: expected " + what);
      throw in.error(t[i].line, "unexpected " + show(t[i]) + " in an expression (expected " + what + ")");
    }

    double finite(double v, const Token& at, const std::string& what) const {
      if (!std::isfinite(v)) throw in.error(at.line, what + " at " + show(at) + " is not a finite number");
      return v;
    }

    double expr() {
      Nest nest(in, i < t.size() ? t[i].line : line);
      double v = and_expr();
      while (punct("||")) {
        ++i;
        const double r = and_expr();
        v = (v != 0 || r != 0) ? 1 : 0;
      }
      return v;
    }
    double and_expr() {
      double v = cmp();
      while (punct("&&")) {
        ++i;
        const double r = cmp();
        v = (v != 0 && r != 0) ? 1 : 0;
      }
      return v;
    }
    double cmp() {
      double v = add();
      static const char* const ops[] = {"<", ">", "<=", ">=", "==", "!="};
      for (const char* op : ops)
        if (punct(op)) {
          ++i;
          const double r = add();
          const std::string o = op;
          if (o == "<") return v < r;
          if (o == ">") return v > r;
          if (o == "<=") return v <= r;
          if (o == ">=") return v >= r;
          if (o == "==") return v == r;
          return v != r;
        }
      return v;
    }
    double add() {
      double v = mul();
      while (punct("+") || punct("-")) {
        const Token op = t[i++];
        const double r = mul();
        v = finite(op.text == "+" ? v + r : v - r, op, "the result");
      }
      return v;
    }
    double mul() {
      double v = unary();
      while (punct("*") || punct("/")) {
        const Token op = t[i++];
        const double r = unary();
        if (op.text == "/" && r == 0) throw in.error(op.line, "division by zero at " + show(op));
        v = finite(op.text == "*" ? v * r : v / r, op, "the result");
      }
      return v;
    }
    double unary() {
      Nest nest(in, i < t.size() ? t[i].line : line);
      return unary_inner();
    }
    double unary_inner() {
      if (punct("-")) {
        ++i;
        return -unary();
      }
      if (punct("+")) {
        ++i;
        return unary();
      }
      if (punct("!")) {
        ++i;
        return unary() == 0 ? 1 : 0;
      }
      return power();
    }
    double power() {
      double v = primary();
      if (punct("^")) {
        const Token op = t[i++];
        const double r = unary();  // right-associative; -2^2 is -(2^2)
        if (v < 0 && r != std::trunc(r)) throw in.error(op.line, "a negative number to a fractional power at " + show(op));
        if (v == 0 && r < 0) throw in.error(op.line, "division by zero at " + show(op) + " (0 to a negative power)");
        v = finite(std::pow(v, r), op, "the power");
      }
      return v;
    }
    double primary() {
      if (i >= t.size()) unexpected("a number, a name or '('");
      if (++in.steps > kSteps)
        throw in.error(t[i].line, "evaluating the input takes more than " + std::to_string(kSteps) +
                                      " steps (deferred definitions re-evaluated too often)");
      const Token& tok = t[i];
      if (tok.kind == Kind::number) {
        ++i;
        double v = 0;
        if (!parse_decimal(tok.text, v)) throw in.error(tok.line, show(tok) + " is not a finite number");
        return v;
      }
      if (punct("(")) {
        ++i;
        const double v = expr();
        if (!punct(")")) unexpected("')'");
        ++i;
        return v;
      }
      if (tok.kind == Kind::name) {
        ++i;
        const std::string up = upper(tok.text);
        if (punct("(")) return call(tok, up);
        if (up == "TRUE") return 1;
        if (up == "FALSE") return 0;
        return in.value_of(tok, at);
      }
      if (tok.kind == Kind::string) throw in.error(tok.line, "a string " + show(tok) + " where a number is expected");
      unexpected("a number, a name or '('");
    }
    double call(const Token& fn, const std::string& up) {
      ++i;  // '('
      std::vector<double> args;
      if (!punct(")")) {
        for (;;) {
          args.push_back(expr());
          if (punct(",")) {
            ++i;
            continue;
          }
          break;
        }
      }
      if (!punct(")")) unexpected("')' closing " + show(fn));
      ++i;
      auto need = [&](size_t n) {
        if (args.size() != n)
          throw in.error(fn.line, show(fn) + " takes " + std::to_string(n) + " argument" + (n == 1 ? "" : "s") +
                                      ", got " + std::to_string(args.size()));
      };
      auto domain = [&](bool ok) {
        if (!ok) throw in.error(fn.line, show(fn) + ": argument out of its domain");
      };
      using F1 = double (*)(double);
      // OPAL's functions of one argument (its Expressions.cpp; LOG is the natural logarithm).
      static const std::map<std::string, F1> one = {
          {"SQRT", [](double x) { return std::sqrt(x); }},   {"SIN", [](double x) { return std::sin(x); }},
          {"COS", [](double x) { return std::cos(x); }},     {"TAN", [](double x) { return std::tan(x); }},
          {"ASIN", [](double x) { return std::asin(x); }},   {"ACOS", [](double x) { return std::acos(x); }},
          {"ATAN", [](double x) { return std::atan(x); }},   {"EXP", [](double x) { return std::exp(x); }},
          {"LOG", [](double x) { return std::log(x); }},     {"ABS", [](double x) { return std::fabs(x); }},
          {"TRUNC", [](double x) { return std::trunc(x); }}, {"ROUND", [](double x) { return std::round(x); }},
          {"FLOOR", [](double x) { return std::floor(x); }}, {"CEIL", [](double x) { return std::ceil(x); }},
          {"ERF", [](double x) { return std::erf(x); }},
          {"SIGN", [](double x) { return x > 0 ? 1.0 : (x < 0 ? -1.0 : 0.0); }},
      };
      auto f = one.find(up);
      if (f != one.end()) {
        need(1);
        const double x = args[0];
        if (up == "SQRT") domain(x >= 0);
        if (up == "LOG") domain(x > 0);
        if (up == "ASIN" || up == "ACOS") domain(x >= -1 && x <= 1);
        return finite(f->second(x), fn, "the value of " + fn.text + "()");
      }
      if (up == "ATAN2") {
        need(2);
        return std::atan2(args[0], args[1]);
      }
      if (up == "POW") {
        need(2);
        if (args[0] == 0 && args[1] < 0) throw in.error(fn.line, "division by zero in " + show(fn) + " (0 to a negative power)");
        domain(args[0] >= 0 || args[1] == std::trunc(args[1]));
        return finite(std::pow(args[0], args[1]), fn, "the value of " + fn.text + "()");
      }
      if (up == "MOD") {
        need(2);
        if (args[1] == 0) throw in.error(fn.line, "division by zero in " + show(fn));
        return std::fmod(args[0], args[1]);
      }
      if (up == "MAX" || up == "MIN") {
        need(2);
        double v = args[0];
        for (double a : args) v = up == "MAX" ? std::max(v, a) : std::min(v, a);
        return v;
      }
      throw in.error(fn.line, "unknown function " + show(fn));
    }
  };

  double value_of(const Token& tok, long at) const {
    const std::string up = upper(tok.text);
    if (up == "OPALVERSION") return version;
    auto k = constants().find(up);
    if (k != constants().end()) return k->second;
    const Definition* d = definition(up, at);
    if (!d) {
      if (definition(up, kEnd))
        throw error(tok.line, "variable " + show(tok) + " is used before its definition (line " +
                                  std::to_string(definition(up, kEnd)->line) + "; ':=' defers an expression)");
      throw error(tok.line, "undefined variable " + show(tok));
    }
    if (d->type == "STRING") throw error(tok.line, "string variable " + show(tok) + " where a number is expected");
    if (!d->deferred) return d->value;
    for (size_t j = 0; j < evaluating.size(); ++j)
      if (evaluating[j] == up) {
        std::string chain;
        for (size_t m = j; m < evaluating.size(); ++m) chain += definition(evaluating[m], at)->spelled + " -> ";
        throw error(tok.line, "circular definition of " + show(tok) + ": " + chain + tok.text);
      }
    // A deferred value depends only on its definition and the definitions in force where it
    // is used: remembered, so definitions built on each other twice over stay linear.
    auto hit = memo.find({d, at});
    if (hit != memo.end()) return hit->second;
    Nest nest(*this, tok.line);
    evaluating.push_back(up);
    double value = 0;
    try {
      value = d->type == "BOOL" ? (eval_bool_tokens(d->expr, d->line, at) ? 1 : 0) : eval_tokens(d->expr, d->line, at);
    } catch (...) {
      evaluating.pop_back();
      throw;
    }
    evaluating.pop_back();
    memo[{d, at}] = value;
    return value;
  }

  double eval_tokens(const Tokens& t, long line, long at) const {
    Parser p{*this, t, at, 0, line};
    const double v = p.expr();
    if (p.i != t.size()) p.unexpected("an operator or the end of the value");
    return v;
  }

  bool eval_bool_tokens(const Tokens& t, long line, long at) const {
    if (t.size() == 1 && t[0].kind == Kind::string) {
      const std::string up = upper(t[0].text);
      if (up == "TRUE") return true;
      if (up == "FALSE") return false;
    }
    return eval_tokens(t, line, at) != 0;
  }
};

Input::Input(const std::string& text, const std::string& name, double opal_version) : impl_(new Impl) {
  impl_->name = name;
  impl_->version = opal_version;
  impl_->lex(text);
  impl_->parse_block(true, 0);
  if (!impl_->stopped && !impl_->at_end()) throw impl_->error(impl_->peek().line, "unbalanced " + show(impl_->peek()));
}
Input::~Input() = default;
Input::Input(Input&&) noexcept = default;
Input& Input::operator=(Input&&) noexcept = default;

const std::vector<Command>& Input::commands() const { return impl_->commands; }
const std::vector<Note>& Input::notes() const { return impl_->notes; }
const std::string& Input::name() const { return impl_->name; }

double Input::number(const Attribute& a) const {
  if (a.value.empty()) throw impl_->error(a.line, "attribute " + quote(a.spelled) + " needs a number");
  return impl_->eval_tokens(a.value, a.line, impl_->when(a));
}

std::string Input::string(const Attribute& a) const {
  if (a.value.size() == 1) {
    const Token& t = a.value[0];
    if (t.kind == Kind::string) return t.text;
    if (t.kind == Kind::name) {
      const Definition* d = impl_->definition(upper(t.text), impl_->when(a));
      if (d && d->type == "STRING") return d->expr[0].text;
      return upper(t.text);  // OPAL reads an unquoted word upper-cased
    }
  }
  throw impl_->error(a.line, "attribute " + quote(a.spelled) + " needs a string, got " +
                                 (a.value.empty() ? std::string("nothing") : show(a.value[0])));
}

bool Input::boolean(const Attribute& a) const {
  if (a.value.empty()) return true;
  return impl_->eval_bool_tokens(a.value, a.line, impl_->when(a));
}

std::vector<double> Input::numbers(const Attribute& a) const {
  if (a.value.empty()) throw impl_->error(a.line, "attribute " + quote(a.spelled) + " needs numbers");
  const Tokens& v = a.value;
  if (!(v.front().kind == Kind::punct && v.front().text == "{")) return {number(a)};
  if (!(v.back().kind == Kind::punct && v.back().text == "}"))
    throw impl_->error(a.line, "attribute " + quote(a.spelled) + ": an array is {a, b, ...}");
  std::vector<double> out;
  const size_t last = v.size() - 1;  // the closing '}'
  for (size_t i = 1; i < last;) {
    const size_t comma = top_level_comma(v, i, last);
    if (comma == i) throw impl_->error(v[i].line, "empty element before " + show(v[i]) + " in " + quote(a.spelled));
    out.push_back(impl_->eval_tokens(Tokens(v.begin() + static_cast<long>(i), v.begin() + static_cast<long>(comma)),
                                      v[i].line, impl_->when(a)));
    i = comma + 1;
    if (comma + 1 == last) throw impl_->error(v.back().line, "empty element at the end of " + quote(a.spelled));
  }
  return out;
}

std::vector<std::string> Input::names(const Attribute& a) const {
  std::vector<std::string> out;
  const Tokens& v = a.value;
  if (v.empty()) throw impl_->error(a.line, "attribute " + quote(a.spelled) + " needs names");
  size_t b = 0, e = v.size();
  if (v.front().kind == Kind::punct && (v.front().text == "{" || v.front().text == "(")) {
    const std::string close = v.front().text == "{" ? "}" : ")";
    if (!(v.back().kind == Kind::punct && v.back().text == close))
      throw impl_->error(a.line, "attribute " + quote(a.spelled) + ": a list is {a, b, ...}");
    b = 1;
    e = v.size() - 1;
  }
  bool want_name = true;
  for (size_t i = b; i < e; ++i) {
    const Token& t = v[i];
    if (want_name && (t.kind == Kind::name || t.kind == Kind::string)) {
      out.push_back(t.text);
      want_name = false;
    } else if (!want_name && t.kind == Kind::punct && t.text == ",") {
      want_name = true;
    } else {
      throw impl_->error(t.line, "unexpected " + show(t) + " in the list " + quote(a.spelled));
    }
  }
  if (want_name && !out.empty()) throw impl_->error(v.back().line, "list " + quote(a.spelled) + " ends with ','");
  return out;
}

double Input::variable(const std::string& n, long line) const {
  Token t;
  t.kind = Kind::name;
  t.text = n;
  t.line = line;
  return impl_->value_of(t, impl_->run_at);
}

void Input::set_evaluation_point(long seq) { impl_->run_at = seq; }


}  // namespace turnfit::opal
