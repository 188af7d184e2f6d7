// The HMI's settings (config/cellsight.yaml, section hmi; app/config reads them). A plain struct: hmi/ does not
// depend on the configuration reader.
#pragma once

#include <string>

namespace cellsight::hmi {

struct HmiParams {
  bool enabled = true;
  std::string bind_address = "127.0.0.1";  // viewing without login only from this machine; 0.0.0.0 for the plant
  int port = 8080;
  // NAME:ROLE:HASH lines written by `cellsight hmi-user`; relative to the configuration file's folder.
  std::string users_file = "hmi-users";
  int max_clients = 16;            // connections served at once (each a civetweb thread); live streams get 3/4
  int session_idle_minutes = 480;  // a shift
  int max_sessions = 32;
  int max_failed_logins = 10;  // in a row from one address; then it is locked out
  int lockout_s = 300;
  int max_request_bytes = 65536;  // larger bodies get 413 before they are read
  int history = 200;              // results kept for the live page and /api/results
  // Review: unknown passes kept on disk (<models>/review) for the operator, at most review_keep (oldest removed);
  // teach passes are kept whatever review_unknown says. keep_slots: scans (16 MB each) the loop can hand over
  // before the writer has stored them; beyond, a scan is not kept (counted).
  bool review_unknown = true;
  int review_keep = 100;
  int keep_slots = 2;
};

}  // namespace cellsight::hmi
