#include "cli/hmi_user_mode.hpp"

#include <termios.h>
#include <unistd.h>

#include <cstdio>
#include <iostream>

#include "cli/cli.hpp"
#include "cli/mode_args.hpp"
#include "hmi/users.hpp"

namespace cellsight::cli {

const char* const kHmiUserUsage =
    "  hmi-user NAME --role operator|maintenance   set (or replace) an account of the operator's screen; the\n"
    "        password (8-128 characters) is read from standard input, without echo on a terminal\n"
    "  hmi-user --list   the accounts (name and role) of hmi.users_file\n";

namespace {

int fail(int code, const std::string& why) {
  std::fprintf(stderr, "cellsight hmi-user: %s\n", why.c_str());
  return code;
}

// One line from standard input; on a terminal asked for twice with echo off.
bool read_password(std::string& out, std::string& error) {
  const bool tty = ::isatty(STDIN_FILENO) == 1;
  termios saved{};
  if (tty && ::tcgetattr(STDIN_FILENO, &saved) == 0) {
    termios quiet = saved;
    quiet.c_lflag &= ~static_cast<tcflag_t>(ECHO);
    ::tcsetattr(STDIN_FILENO, TCSAFLUSH, &quiet);
  }
  std::string again;
  if (tty) std::fprintf(stderr, "password: ");
  const bool got = static_cast<bool>(std::getline(std::cin, out));
  if (tty && got) {
    std::fprintf(stderr, "\nagain: ");
    std::getline(std::cin, again);
    std::fprintf(stderr, "\n");
  }
  if (tty) ::tcsetattr(STDIN_FILENO, TCSAFLUSH, &saved);
  if (!got) {
    error = "no password on standard input";
    return false;
  }
  if (tty && again != out) {
    error = "the two passwords differ";
    return false;
  }
  return true;
}

}  // namespace

int run_hmi_user(const std::vector<std::string>& args, const app::Config& config) {
  ModeArgs parsed;
  std::string error;
  if (!parse_mode_args(args, {"--role"}, {"--list"}, parsed, error)) return fail(kExitUsage, error);
  const std::string& path = config.hmi.users_file;
  if (parsed.has("--list")) {
    auto users = hmi::load_users(path);
    if (!users) return fail(kExitUsage, users.error().message);
    if (users->empty()) std::printf("no accounts in %s\n", path.c_str());
    for (const auto& u : *users) std::printf("%s %s\n", u.name.c_str(), hmi::to_string(u.role));
    return kExitOk;
  }
  if (parsed.positional.size() != 1 || parsed.value("--role") == nullptr) {
    return fail(kExitUsage, std::string("expected NAME --role operator|maintenance\n") + kHmiUserUsage);
  }
  const hmi::Role role = hmi::role_from_string(*parsed.value("--role"));
  if (role == hmi::Role::kNone) return fail(kExitUsage, "--role must be operator or maintenance");
  std::string password;
  if (!read_password(password, error)) return fail(kExitUsage, error);
  if (auto ok = hmi::set_user(path, parsed.positional[0], role, password); !ok) {
    return fail(kExitUsage, ok.error().message);
  }
  std::printf("%s: %s is %s\n", path.c_str(), parsed.positional[0].c_str(), hmi::to_string(role));
  return kExitOk;
}

}  // namespace cellsight::cli
