#include "hmi/users.hpp"

#include <crypt.h>
#include <sys/stat.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <memory>
#include <sstream>

#include "base/atomic_file.hpp"

namespace cellsight::hmi {
namespace {

constexpr std::size_t kMaxName = 32, kMinPassword = 8, kMaxPassword = 128;

bool valid_name(std::string_view name) {
  if (name.empty() || name.size() > kMaxName) return false;
  return std::all_of(name.begin(), name.end(), [](char c) {
    return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_' || c == '.' ||
           c == '-';
  });
}

// crypt_rn with its 32 KiB work area on the heap (struct crypt_data is too big for a server thread's stack).
std::string crypt_text(std::string_view password, const char* setting) {
  auto data = std::make_unique<crypt_data>();
  const std::string phrase(password);
  const char* out = ::crypt_rn(phrase.c_str(), setting, data.get(), sizeof *data);
  if (out == nullptr || out[0] == '*') return {};
  return out;
}

// A valid yescrypt hash of a random password: what an unknown name is checked against.
const std::string& dummy_hash() {
  static const std::string hash = [] {
    char setting[CRYPT_GENSALT_OUTPUT_SIZE];
    if (::crypt_gensalt_rn("$y$", 0, nullptr, 0, setting, sizeof setting) == nullptr) return std::string();
    return crypt_text("not a password of anyone", setting);
  }();
  return hash;
}

}  // namespace

Role role_from_string(std::string_view text) {
  if (text == "operator") return Role::kOperator;
  if (text == "maintenance") return Role::kMaintenance;
  return Role::kNone;
}

Expected<std::vector<User>> load_users(const std::string& path) {
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) return std::vector<User>{};
  if (!std::filesystem::is_regular_file(path, ec)) return make_error(path + ": not a regular file");
  std::ifstream in(path);
  if (!in) return make_error(path + ": cannot read: " + std::strerror(errno));
  std::vector<User> users;
  std::string line;
  int number = 0;
  while (std::getline(in, line)) {
    ++number;
    if (line.empty() || line[0] == '#') continue;
    const std::string where = path + ":" + std::to_string(number) + ": ";
    const auto a = line.find(':');
    const auto b = a == std::string::npos ? a : line.find(':', a + 1);
    if (b == std::string::npos) return make_error(where + "expected NAME:ROLE:HASH");
    User u{line.substr(0, a), role_from_string(line.substr(a + 1, b - a - 1)), line.substr(b + 1)};
    if (!valid_name(u.name))
      return make_error(where + "'" + u.name + "' is not a user name (1-32 of A-Z a-z 0-9 _ . -)");
    if (u.role == Role::kNone) return make_error(where + "role must be operator or maintenance");
    if (u.hash.rfind("$y$", 0) != 0) return make_error(where + "the hash is not a yescrypt hash ($y$...)");
    for (const auto& other : users) {
      if (other.name == u.name) return make_error(where + "user '" + u.name + "' appears twice");
    }
    users.push_back(std::move(u));
  }
  return users;
}

Status set_user(const std::string& path, const std::string& name, Role role, const std::string& password) {
  if (!valid_name(name)) return make_error("'" + name + "' is not a user name (1-32 of A-Z a-z 0-9 _ . -)");
  if (role == Role::kNone) return make_error("role must be operator or maintenance");
  if (password.size() < kMinPassword || password.size() > kMaxPassword) {
    return make_error("the password must have 8 to 128 characters");
  }
  auto users = load_users(path);
  if (!users) return users.error();
  char setting[CRYPT_GENSALT_OUTPUT_SIZE];
  if (::crypt_gensalt_rn("$y$", 0, nullptr, 0, setting, sizeof setting) == nullptr) {
    return make_error(std::string("cannot make a salt: ") + std::strerror(errno));
  }
  const std::string hash = crypt_text(password, setting);
  if (hash.empty()) return make_error("yescrypt failed");
  bool replaced = false;
  for (auto& u : *users) {
    if (u.name == name) {
      u.role = role;
      u.hash = hash;
      replaced = true;
    }
  }
  if (!replaced) users->push_back({name, role, hash});
  std::ostringstream text;
  text << "# cellsight HMI accounts (NAME:ROLE:yescrypt hash); written by `cellsight hmi-user`\n";
  for (const auto& u : *users) text << u.name << ':' << to_string(u.role) << ':' << u.hash << '\n';
  if (Status s = base::write_file_atomic(path, text.str()); !s) return s;
  if (::chmod(path.c_str(), S_IRUSR | S_IWUSR) != 0) {
    return make_error(path + ": cannot make it private (chmod 600): " + std::strerror(errno));
  }
  return {};
}

Role check_password(const std::vector<User>& users, std::string_view name, std::string_view password) {
  const auto it = std::find_if(users.begin(), users.end(), [&](const User& u) { return u.name == name; });
  const std::string& hash = it == users.end() ? dummy_hash() : it->hash;
  if (hash.empty() || password.size() > kMaxPassword) return Role::kNone;
  const std::string computed = crypt_text(password, hash.c_str());
  // Compared in full, whatever differs first.
  if (computed.size() != hash.size()) return Role::kNone;
  unsigned char diff = 0;
  for (std::size_t i = 0; i < hash.size(); ++i) diff |= static_cast<unsigned char>(computed[i] ^ hash[i]);
  return diff == 0 && it != users.end() ? it->role : Role::kNone;
}

}  // namespace cellsight::hmi
