#pragma once
// Reading a TOML table key by key with errors that name file:line and the key: wrong types,
// out-of-range values and unknown keys (a typo must not fall back to a default silently).
// The first problem is kept; getters return the default after it, so parsing reads straight.
// Used by the scene files (sim/) and the daemon's config (daemon/).

#include <fmt/format.h>
#include <toml++/toml.h>

#include <cmath>
#include <set>
#include <sstream>
#include <string>
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
  [[nodiscard]] const std::string& file() const { return file_; }
  std::string* errorSink() const { return error_; }
  [[nodiscard]] std::string child(const char* key) const { return name(key); }

 private:
  [[nodiscard]] std::string name(const char* key) const {
    return prefix_.empty() ? key : prefix_ + "." + key;
  }
  static std::string text(const toml::node* n) {
    std::ostringstream s;
    n->visit([&s](const auto& v) { s << v; });
    return s.str();
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
inline bool parseToml(const std::string& text, const std::string& file, toml::table& out,
                      std::string& error) {
  try {
    out = toml::parse(text, file);
  } catch (const toml::parse_error& e) {
    error = fmt::format("{}:{}: {}", file, e.source().begin.line, e.description());
    return false;
  }
  return true;
}

}  // namespace pulsetrack::cfg
