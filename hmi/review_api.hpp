// The Review page's routes and the screen's teach session (issue 14):
//   GET  /api/review                  the kept scans, newest first (ReviewStore)
//   GET  /api/review/ID/depth.png     an entry's depth image
//   POST /api/review/teach            {ids, name, part_id}: teach those scans as a part (operator)
//   POST /api/review/discard          {ids} (operator)
//   GET  /api/teach                   the teach session
//   POST /api/teach/start             {name, part_id, passes}: ENTER_TEACH through the loop's command path; the next
//                                     `passes` passes are kept and then taught (operator)
//   POST /api/teach/stop              {teach_now}: LEAVE_TEACH; with teach_now what was collected is taught
// Teaching runs `cellsight teach` as a job (JobRunner); the taught entries leave the Review ring when it succeeded.
#pragma once

#include <cstdint>
#include <memory>
#include <mutex>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "drivers/modbus/register_map.hpp"
#include "hmi/jobs.hpp"
#include "hmi/review_store.hpp"
#include "hmi/routes.hpp"

namespace cellsight::hmi {

// What the screen may ask of the running cell: the loop's command path (ProductionLoop::post_command).
class CellCommands {
 public:
  enum class Fate : std::uint8_t { kPending, kDone, kRefused };
  virtual ~CellCommands() = default;
  virtual bool post(drivers::CommandCode command, std::uint32_t arg) = 0;  // false: the last one is still pending
  [[nodiscard]] virtual Fate fate() const = 0;
  [[nodiscard]] virtual std::uint16_t teaching_part_id() const = 0;
};

class ReviewApi {
 public:
  // All borrowed; they outlive the server. on_stored of `store` is taken by this object.
  ReviewApi(ReviewStore& store, JobRunner& jobs, CellCommands& cell);
  [[nodiscard]] std::vector<Route> routes();
  [[nodiscard]] nlohmann::json teach_json() const;

 private:
  int list(const Request& r);
  int image(const Request& r);
  int teach_picked(const Request& r);
  int discard(const Request& r);
  int teach_start(const Request& r);
  int teach_stop(const Request& r);
  void on_stored(const ReviewEntry& entry);
  // Leaves teach mode through the loop (waits up to a second for it to take the command).
  bool command(drivers::CommandCode code, std::uint32_t arg);
  // Starts `teach --part NAME --id N scans`; the entries leave the ring when it succeeds.
  // for_session: the teach session follows the job (its state becomes done or failed when it ends).
  Expected<std::uint64_t> start_teach(const std::string& name, int part_id, const std::vector<std::uint64_t>& ids,
                                      bool for_session);

  ReviewStore& store_;
  JobRunner& jobs_;
  CellCommands& cell_;
  mutable std::mutex mutex_;  // the session
  struct Session {
    std::string state = "idle";  // idle | collecting | teaching | done | failed | stopped
    std::string name;
    int part_id = 0;
    int wanted = 0;
    std::vector<std::uint64_t> collected;
    std::string message;
    std::uint64_t job = 0;
  } session_;
};

}  // namespace cellsight::hmi
