// The HMI's accounts: a file of its own, outside the configuration (maintenance staff copy configs around; a
// password hash should not travel with them), one line per user "NAME:ROLE:HASH". HASH is crypt(3)'s yescrypt
// ("$y$..." from libxcrypt, Debian's libcrypt): salted and deliberately slow, so a stolen file is no list of
// passwords. `cellsight hmi-user` writes the file (atomically, mode 0600); run reads it at start-up.
#pragma once

#include <string>
#include <string_view>
#include <vector>

#include "base/result.hpp"

namespace cellsight::hmi {

// operator: live view, review, teaching; maintenance: also delete, retrain, debug, settings.
enum class Role : std::uint8_t { kNone, kOperator, kMaintenance };

[[nodiscard]] constexpr const char* to_string(Role role) {
  switch (role) {
    case Role::kOperator: return "operator";
    case Role::kMaintenance: return "maintenance";
    case Role::kNone: break;
  }
  return "none";
}
[[nodiscard]] Role role_from_string(std::string_view text);  // kNone when not a role

struct User {
  std::string name;
  Role role = Role::kNone;
  std::string hash;
};

// A missing file is no accounts (viewing from 127.0.0.1 only); a malformed line refuses the whole file, naming
// file, line and reason.
[[nodiscard]] Expected<std::vector<User>> load_users(const std::string& path);
// Adds or replaces `name` with a fresh salt; names are 1-32 of [A-Za-z0-9_.-], passwords 8-128 bytes.
[[nodiscard]] Status set_user(const std::string& path, const std::string& name, Role role, const std::string& password);
// The user's role when the password is right, kNone otherwise (also for an unknown name, after the same work, so
// the answer's time does not tell which names exist).
[[nodiscard]] Role check_password(const std::vector<User>& users, std::string_view name, std::string_view password);

}  // namespace cellsight::hmi
