#pragma once
// The console's users: a file of one line per user, set at install (`pulsetrack console-user`),
//   NAME:ROLE:pbkdf2-sha256:ITERATIONS:SALT_HEX:HASH_HEX
// ROLE is "operator" (may command the appliance) or "viewer" (sees it only). The password is
// never stored: PBKDF2-HMAC-SHA256 (OpenSSL) with a random 16-byte salt; compared in constant
// time. Lines starting with '#' and blank lines are ignored.

#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "pulsetrack/vision/error.hpp"

namespace pulsetrack::console {

enum class Role { kViewer, kOperator };
const char* toString(Role r);

struct User {
  std::string name;
  Role role = Role::kViewer;
  int iterations = 0;
  std::vector<unsigned char> salt, hash;
};

class Credentials {
 public:
  // Errors name the file and the line. A file readable by others than its owner is refused
  // (it holds password hashes), as is an empty one.
  static vision::Result<Credentials> load(const std::filesystem::path& file);
  // The user's role when the password is right; nothing otherwise (an unknown user costs the
  // same time as a wrong password).
  [[nodiscard]] std::optional<Role> verify(const std::string& user,
                                           const std::string& password) const;
  [[nodiscard]] const std::vector<User>& users() const { return users_; }

 private:
  std::vector<User> users_;
  User dummy_;  // verified against when the user is unknown
};

// Adds or replaces a user in `file` (created with mode 0600). Names: 1-64 of [A-Za-z0-9_.-];
// passwords: at least 8 characters.
vision::Result<void> setUser(const std::filesystem::path& file, const std::string& name, Role role,
                             const std::string& password, int iterations = 200000);

}  // namespace pulsetrack::console
