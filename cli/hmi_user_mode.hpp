// `cellsight hmi-user`: the operator's screen's accounts (hmi/users.hpp).
#pragma once

#include <string>
#include <vector>

#include "app/config.hpp"

namespace cellsight::cli {

extern const char* const kHmiUserUsage;
// hmi-user NAME --role operator|maintenance: the password from standard input (asked for without echo on a
// terminal); hmi-user --list: names and roles. The file is hmi.users_file of the configuration.
int run_hmi_user(const std::vector<std::string>& args, const app::Config& config);

}  // namespace cellsight::cli
