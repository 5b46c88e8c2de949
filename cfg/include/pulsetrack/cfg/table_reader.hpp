#pragma once
// Reading a TOML table key by key with errors that name file:line and the key: wrong types,
// out-of-range values and unknown keys (a typo must not fall back to a default silently).
// The first problem is kept; getters return the default after it, so parsing reads straight.
// Used by the scene files (sim/) and the daemon's config (daemon/).

#include <fmt/format.h>
#include <toml++/toml.h>

#include <cmath>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <set>
#include <string>
#include <string_view>
#include <system_error>
#include <vector>

namespace pulsetrack::cfg {

class TableReader {
 public:
  TableReader(const toml::table& table, std::string file, std::string prefix, std::string* error)
      : table_(table), file_(std::move(file)), prefix_(std::move(prefix)), error_(error) {}

  double number(const char* key, double def, double lo, double hi) {
    seen_.insert(key);
    const toml::node* n = table_.get(key);
    if (n == nullptr) return def;
    const auto v = n->value<double>();
    if (!v || !std::isfinite(*v) || *v < lo || *v > hi) {
      fault(n,
            fmt::format("{}: expected a number in [{}, {}], got {}", name(key), lo, hi, text(n)));
      return def;
    }
    return *v;
  }
  int integer(const char* key, int def, int lo, int hi) {
    seen_.insert(key);
    const toml::node* n = table_.get(key);
    if (n == nullptr) return def;
    const auto v = n->value_exact<int64_t>();
    if (!v || *v < lo || *v > hi) {
      fault(n,
            fmt::format("{}: expected an integer in [{}, {}], got {}", name(key), lo, hi, text(n)));
      return def;
    }
    return static_cast<int>(*v);
  }
  bool boolean(const char* key, bool def) {
    seen_.insert(key);
    const toml::node* n = table_.get(key);
    if (n == nullptr) return def;
    const auto v = n->value_exact<bool>();
    if (!v) {
      fault(n, fmt::format("{}: expected true or false, got {}", name(key), text(n)));
      return def;
    }
    return *v;
  }
  std::string string(const char* key, const std::string& def,
                     const std::set<std::string>& allowed = {}) {
    seen_.insert(key);
    const toml::node* n = table_.get(key);
    if (n == nullptr) return def;
    const auto v = n->value_exact<std::string>();
    if (!v || (!allowed.empty() && !allowed.contains(*v))) {
      std::string list;
      for (const auto& a : allowed) list += (list.empty() ? "" : ", ") + a;
      fault(n, fmt::format("{}: expected {}, got {}", name(key),
                           allowed.empty() ? std::string("a string") : "one of " + list, text(n)));
      return def;
    }
    return *v;
  }
  std::vector<double> numbers(const char* key, const std::vector<double>& def, size_t count_lo,
                              size_t count_hi, double lo, double hi) {
    seen_.insert(key);
    const toml::node* n = table_.get(key);
    if (n == nullptr) return def;
    const toml::array* a = n->as_array();
    std::vector<double> out;
    if (a != nullptr) {
      for (const toml::node& e : *a) {
        const auto v = e.value<double>();
        if (!v || *v < lo || *v > hi) {
          out.clear();
          break;
        }
        out.push_back(*v);
      }
    }
    if (a == nullptr || out.size() < count_lo || out.size() > count_hi ||
        (out.empty() && count_lo > 0) || (a != nullptr && out.size() != a->size())) {
      fault(n, fmt::format("{}: expected {} to {} numbers in [{}, {}]", name(key), count_lo,
                           count_hi, lo, hi));
      return def;
    }
    return out;
  }
  const toml::table* table(const char* key) {
    seen_.insert(key);
    const toml::node* n = table_.get(key);
    if (n == nullptr) return nullptr;
    if (!n->is_table()) {
      fault(n, fmt::format("{}: expected a table", name(key)));
      return nullptr;
    }
    return n->as_table();
  }
  const toml::array* arrayOfTables(const char* key) {
    seen_.insert(key);
    const toml::node* n = table_.get(key);
    if (n == nullptr) return nullptr;
    if (!n->is_array_of_tables()) {
      fault(n, fmt::format("{}: expected an array of tables ([[{}]])", name(key), name(key)));
      return nullptr;
    }
    return n->as_array();
  }
  // Unknown keys are errors: a typo must not silently fall back to a default.
  void finish() {
    for (const auto& [k, v] : table_) {
      if (!seen_.contains(std::string(k.str()))) {
        fault(&v, fmt::format("unknown key '{}'", name(std::string(k.str()).c_str())));
      }
    }
  }
  // A rule between values: when `ok` is false, the error names the key's line (it must be
  // present) and says `what`.
  void require(const char* key, bool ok, const std::string& what) {
    if (ok) return;
    if (const toml::node* n = table_.get(key)) fault(n, fmt::format("{}: {}", name(key), what));
  }
  [[nodiscard]] const std::string& file() const { return file_; }
  std::string* errorSink() const { return error_; }
  [[nodiscard]] std::string child(const char* key) const { return name(key); }

 private:
  [[nodiscard]] std::string name(const char* key) const {
    return prefix_.empty() ? key : prefix_ + "." + key;
  }
  // The offending value, short, for a message. Not through toml++'s formatter: in 3.3 it casts
  // log10 of a float below 1 to size_t when it lays out an array or a table (undefined
  // behaviour, fuzz_scene), and a whole table is no help in a message anyway.
  static std::string text(const toml::node* n) {
    if (const auto* v = n->as_string()) return fmt::format("\"{}\"", v->get().substr(0, 40));
    if (const auto* v = n->as_integer()) return fmt::format("{}", v->get());
    if (const auto* v = n->as_floating_point()) return fmt::format("{}", v->get());
    if (const auto* v = n->as_boolean()) return v->get() ? "true" : "false";
    if (const auto* v = n->as_array()) return fmt::format("an array of {}", v->size());
    if (n->is_table()) return "a table";
    return "a date or time";
  }
  void fault(const toml::node* n, const std::string& what) {
    if (!error_->empty()) return;
    *error_ = fmt::format("{}:{}: {}", file_, n->source().begin.line, what);
  }

  const toml::table& table_;
  std::string file_;
  std::string prefix_;
  std::string* error_;
  std::set<std::string> seen_;
};

// Parses TOML text; a syntax error as "file:line: what".
// TOML allows characters outside ASCII only in strings and comments. toml++ 3.3 (Debian 12)
// reaches a __builtin_unreachable() when it meets one elsewhere (its whitespace test,
// unicode_autogenerated.h: undefined behaviour in the release build; fuzz_daemon_config and
// fuzz_scene found it with a lone U+0497), so such a byte is refused here, before toml++ sees
// it, with the line it is on.
inline bool checkTomlText(const std::string& text, const std::string& file, std::string& error) {
  size_t line = 1;
  const size_t n = text.size();
  // A UTF-8 byte order mark (Windows editors write one): toml++ skips it.
  const size_t start = text.starts_with("\xEF\xBB\xBF") ? 3 : 0;
  // The last character outside strings and comments that is not a space or tab: a quote opens
  // a string only where TOML has one (a value after '=', '[' or ',', a key at a line's start or
  // after '.', '{' or ','). Elsewhere toml++ does not read it as a string either: it reads on
  // as the token before (fuzz_daemon_config: a number directly followed by "...\u039a").
  char prev = '\n';
  for (size_t i = start; i < n; ++i) {
    const char c = text[i];
    const bool opens_string = std::string_view("\n=[,{.").find(prev) != std::string_view::npos;
    if (c != ' ' && c != '\t' && c != '#') prev = c;
    if (c == '\n') {
      ++line;
    } else if (c == '#') {
      while (i + 1 < n && text[i + 1] != '\n') ++i;
    } else if ((c == '"' || c == '\'') && opens_string) {
      const bool multi = i + 2 < n && text[i + 1] == c && text[i + 2] == c;
      i += multi ? 3 : 1;
      for (; i < n; ++i) {
        if (text[i] == '\n') {
          ++line;
          if (!multi) break;  // an unterminated string: toml++ says so
        } else if (c == '"' && text[i] == '\\') {
          if (i + 1 < n && text[i + 1] == '\n') ++line;
          ++i;
        } else if (text[i] == c &&
                   (!multi || (i + 2 < n && text[i + 1] == c && text[i + 2] == c))) {
          if (multi) {
            i += 2;
            // A multi-line string may end in one or two quotes of its own (TOML 1.0).
            for (int extra = 0; extra < 2 && i + 1 < n && text[i + 1] == c; ++extra) ++i;
          }
          break;
        }
      }
    } else if (static_cast<unsigned char>(c) >= 0x80) {
      error = fmt::format(
          "{}:{}: a character outside ASCII outside a string or a comment (TOML "
          "allows them only in \"strings\" and # comments)",
          file, line);
      return false;
    }
  }
  return true;
}

// A project TOML file's text (config, scene, manifest: each a few KB), read whole. More than 1 MiB
// is not one of them; `what` names the kind of file in the messages.
inline bool readTomlText(const std::filesystem::path& path, const char* what, std::string& text,
                         std::string& error) {
  constexpr std::uintmax_t kMaxBytes = 1U << 20;
  std::error_code ec;
  const std::uintmax_t size = std::filesystem::file_size(path, ec);
  if (ec) {
    error = fmt::format("{}: cannot open the {}: {}", path.string(), what, ec.message());
    return false;
  }
  if (size > kMaxBytes) {
    error = fmt::format("{}: {} bytes is not a {} (at most 1 MiB)", path.string(), size, what);
    return false;
  }
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    error = fmt::format("{}: cannot open the {}", path.string(), what);
    return false;
  }
  text.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  if (in.bad()) {
    error = fmt::format("{}: read error", path.string());
    return false;
  }
  return true;
}

inline bool parseToml(const std::string& text, const std::string& file, toml::table& out,
                      std::string& error) {
  if (!checkTomlText(text, file, error)) return false;
  try {
    out = toml::parse(text, file);
  } catch (const toml::parse_error& e) {
    error = fmt::format("{}:{}: {}", file, e.source().begin.line, e.description());
    return false;
  }
  return true;
}

}  // namespace pulsetrack::cfg
