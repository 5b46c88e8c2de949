#include "pulsetrack/console/credentials.hpp"

#include <fmt/format.h>
#include <openssl/crypto.h>
#include <openssl/evp.h>
#include <openssl/rand.h>
#include <sys/stat.h>

#include <fstream>
#include <sstream>

namespace pulsetrack::console {

using vision::fail;

const char* toString(Role r) { return r == Role::kOperator ? "operator" : "viewer"; }

namespace {

constexpr size_t kHashBytes = 32;

std::string hex(const std::vector<unsigned char>& b) {
  std::string out;
  for (const unsigned char c : b) out += fmt::format("{:02x}", c);
  return out;
}

bool unhex(const std::string& s, std::vector<unsigned char>& out) {
  if (s.size() % 2 != 0 || s.empty()) return false;
  out.clear();
  for (size_t i = 0; i < s.size(); i += 2) {
    unsigned v = 0;
    for (size_t k = i; k < i + 2; ++k) {
      const char c = s[k];
      v <<= 4U;
      if (c >= '0' && c <= '9')
        v |= static_cast<unsigned>(c - '0');
      else if (c >= 'a' && c <= 'f')
        v |= static_cast<unsigned>(c - 'a' + 10);
      else
        return false;
    }
    out.push_back(static_cast<unsigned char>(v));
  }
  return true;
}

std::vector<unsigned char> pbkdf2(const std::string& password,
                                  const std::vector<unsigned char>& salt, int iterations) {
  std::vector<unsigned char> out(kHashBytes);
  PKCS5_PBKDF2_HMAC(password.data(), static_cast<int>(password.size()), salt.data(),
                    static_cast<int>(salt.size()), iterations, EVP_sha256(),
                    static_cast<int>(out.size()), out.data());
  return out;
}

bool validName(const std::string& n) {
  if (n.empty() || n.size() > 64) return false;
  for (const char c : n) {
    const bool ok = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') ||
                    c == '_' || c == '.' || c == '-';
    if (!ok) return false;
  }
  return true;
}

std::vector<std::string> split(const std::string& line, char sep) {
  std::vector<std::string> out;
  std::string part;
  std::istringstream ss(line);
  while (std::getline(ss, part, sep)) out.push_back(part);
  if (!line.empty() && line.back() == sep) out.emplace_back();
  return out;
}

}  // namespace

vision::Result<Credentials> Credentials::load(const std::filesystem::path& file) {
  const std::string f = file.string();
  struct stat st {};
  if (stat(f.c_str(), &st) != 0)
    return fail(fmt::format("{}: users file not found (pulsetrack console-user adds one)", f));
  if ((st.st_mode & 077) != 0) {
    return fail(
        fmt::format("{}: readable by others (mode {:o}); it holds password hashes: chmod 600 {}", f,
                    st.st_mode & 0777, f));
  }
  std::ifstream in(file);
  if (!in) return fail(fmt::format("{}: cannot read it", f));
  Credentials c;
  std::string line;
  int n = 0;
  while (std::getline(in, line)) {
    ++n;
    if (line.empty() || line[0] == '#') continue;
    const auto bad = [&](const std::string& why) {
      return fail(fmt::format("{}:{}: {} (expected NAME:ROLE:pbkdf2-sha256:ITERATIONS:SALT:HASH)",
                              f, n, why));
    };
    const std::vector<std::string> p = split(line, ':');
    if (p.size() != 6) return bad(fmt::format("{} fields, not 6", p.size()));
    User u;
    u.name = p[0];
    if (!validName(u.name)) return bad("the name must be 1-64 of A-Z a-z 0-9 _ . -");
    if (p[1] == "operator")
      u.role = Role::kOperator;
    else if (p[1] == "viewer")
      u.role = Role::kViewer;
    else
      return bad(fmt::format("role '{}' (operator or viewer)", p[1].substr(0, 32)));
    if (p[2] != "pbkdf2-sha256") return bad(fmt::format("scheme '{}'", p[2].substr(0, 32)));
    try {
      size_t used = 0;
      u.iterations = std::stoi(p[3], &used);
      if (used != p[3].size() || u.iterations < 1000 || u.iterations > 10'000'000)
        return bad("iterations must be 1000 to 10000000");
    } catch (const std::exception&) {
      return bad("iterations must be a number");
    }
    if (!unhex(p[4], u.salt) || u.salt.size() < 8) return bad("the salt is not hex of >= 8 bytes");
    if (!unhex(p[5], u.hash) || u.hash.size() != kHashBytes)
      return bad("the hash is not 32 bytes of hex");
    for (const User& other : c.users_)
      if (other.name == u.name) return bad(fmt::format("user '{}' a second time", u.name));
    c.users_.push_back(std::move(u));
  }
  if (c.users_.empty())
    return fail(fmt::format("{}: no user (pulsetrack console-user adds one)", f));
  c.dummy_ = c.users_.front();
  return c;
}

std::optional<Role> Credentials::verify(const std::string& user,
                                        const std::string& password) const {
  const User* u = &dummy_;
  bool known = false;
  for (const User& candidate : users_) {
    if (candidate.name == user) {
      u = &candidate;
      known = true;
    }
  }
  const std::vector<unsigned char> h = pbkdf2(password, u->salt, u->iterations);
  const bool same = CRYPTO_memcmp(h.data(), u->hash.data(), kHashBytes) == 0;
  if (!known || !same) return std::nullopt;
  return u->role;
}

vision::Result<void> setUser(const std::filesystem::path& file, const std::string& name, Role role,
                             const std::string& password, int iterations) {
  const std::string f = file.string();
  if (!validName(name)) return fail(fmt::format("user name '{}': 1-64 of A-Z a-z 0-9 _ . -", name));
  if (password.size() < 8) return fail("the password must have at least 8 characters");
  std::vector<std::string> lines;
  if (std::filesystem::exists(file)) {
    std::ifstream in(file);
    if (!in) return fail(fmt::format("{}: cannot read it", f));
    std::string line;
    while (std::getline(in, line)) {
      if (line.rfind(name + ":", 0) == 0) continue;  // replaced
      lines.push_back(line);
    }
  } else {
    lines.emplace_back("# pulsetrack console users: NAME:ROLE:pbkdf2-sha256:ITERATIONS:SALT:HASH");
  }
  std::vector<unsigned char> salt(16);
  if (RAND_bytes(salt.data(), static_cast<int>(salt.size())) != 1)
    return fail("no random bytes from OpenSSL for the salt");
  lines.push_back(fmt::format("{}:{}:pbkdf2-sha256:{}:{}:{}", name, toString(role), iterations,
                              hex(salt), hex(pbkdf2(password, salt, iterations))));
  const std::filesystem::path tmp = file.string() + ".new";
  {
    const mode_t old = umask(077);
    std::ofstream out(tmp, std::ios::trunc);
    umask(old);
    if (!out) return fail(fmt::format("{}: cannot write it", tmp.string()));
    for (const std::string& l : lines) out << l << "\n";
    if (!out.flush()) return fail(fmt::format("{}: write failed", tmp.string()));
  }
  std::error_code ec;
  std::filesystem::permissions(
      tmp, std::filesystem::perms::owner_read | std::filesystem::perms::owner_write, ec);
  std::filesystem::rename(tmp, file, ec);
  if (ec) return fail(fmt::format("{}: cannot replace it: {}", f, ec.message()));
  return {};
}

}  // namespace pulsetrack::console
