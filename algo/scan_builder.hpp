// One pass, frame by frame (DESIGN.md data flow): stripe -> exposure -> triangulation -> scan buffer.
// Pure computation on caller-owned pixels; everything is allocated in the constructor and reused per pass.
#pragma once

#include <cstdint>
#include <vector>

#include "algo/exposure.hpp"
#include "algo/scan.hpp"
#include "algo/sensor_model.hpp"
#include "algo/stripe.hpp"
#include "algo/triangulation.hpp"

namespace cellsight::algo {

struct ScanBuilderParams {
  StripeParams stripe{};
  ExposureParams exposure{};
  double carrier_start_offset_m = 0.65;  // carrier x under the laser at the pass's first encoder count
  std::size_t max_points = 1'000'000;    // scan buffer capacity (a pass is ~0.2-0.5 M points)
  // A stripe piece must run over at least this many consecutive rows (centres within run_continuity_px of the
  // row above) to become points: glints span up to ~5 rows, real surfaces more (6 rows ~ 10 mm).
  int min_run_rows = 6;
  float run_continuity_px = 2.0F;
  // Rows at either end of a run dimmer than this share of the run's mean peak are the blurred end of the line
  // (it spills ~1-2 px past an edge), not surface: they are trimmed.
  float end_taper_ratio = 0.5F;
  // Surfaces nearly edge-on to the rows (a flange toward the camera) make the stripe run along the rows, where one
  // point per row samples it sparsely or not at all. Rows the row pass left wide, broken into short runs, or
  // bright but empty are re-read column by column: each column's vertical centre of gravity gives one point.
  float wide_row_px = 8.0F;        // a row stripe wider than this is looked at column by column too
  int min_column_run = 6;          // consecutive columns in a row-wise piece, like min_run_rows
  int max_column_extent_rows = 6;  // half-maximum extent of one column's peak: a line crossing, not a blob
};

struct FrameOutcome {
  StripeResult stripe = StripeResult::kOk;
  ExposureStep exposure{};
  int points_added = 0;
  float median_width_px = 0.0F;
  bool width_in_band = false;
};

struct PassStats {
  int frames = 0;
  int frames_with_stripe = 0;  // enough valid rows for the exposure loop to act on
  int frames_in_band = 0;      // of those, median width inside the exposure band
  std::size_t points = 0;
  std::size_t dropped_points = 0;  // the scan buffer was full
  std::size_t short_run_rows = 0;  // valid rows discarded as too-short runs (glints, ghost fragments)
  std::size_t tapered_rows = 0;    // valid rows trimmed from run ends
  std::size_t column_points = 0;   // points from row-wise stripe pieces (column pass)
};

class ScanBuilder {
 public:
  // Start-up only: allocates the triangulation table, the stripe profile and the scan buffer.
  ScanBuilder(const ScanBuilderParams& params, const SensorCalibration& calibration);

  // A new part: empties the scan, remembers the encoder count at the pass start and the exposure to begin with.
  void begin_pass(std::int64_t start_counts, std::int32_t exposure_us);

  // Real-time, per frame: no allocation. frame_exposure_us is the exposure the frame was taken with.
  FrameOutcome add_frame(const std::uint8_t* pixels, int width, int height, int stride, std::int32_t frame_exposure_us,
                         std::int64_t encoder_counts);

  [[nodiscard]] const ScanBuffer& scan() const { return scan_; }
  [[nodiscard]] ScanBuffer& scan() { return scan_; }
  [[nodiscard]] const StripeProfile& profile() const { return profile_; }
  [[nodiscard]] const PassStats& stats() const { return stats_; }
  [[nodiscard]] std::int32_t exposure_us() const { return exposure_.exposure_us(); }
  [[nodiscard]] const Triangulator& triangulator() const { return triangulator_; }

 private:
  void emit_run(int first, int last, double travel_m, FrameOutcome& out);
  void column_pass(const std::uint8_t* pixels, int width, int height, int stride, double travel_m, FrameOutcome& out);
  // column_pass()'s steps: the least peak a column's crossing needs, the rows (and their columns) to re-read, and the
  // runs of smoothly continuing columns of a band turned into points.
  [[nodiscard]] double column_min_peak() const;
  void select_column_rows(const std::uint8_t* pixels, int width, int stride, double min_peak);
  void emit_column_runs(int c_lo, int c_hi, int width, double travel_m, FrameOutcome& out);

  ScanBuilderParams params_;
  Triangulator triangulator_;
  StripeProfile profile_;
  ExposureController exposure_;
  ScanBuffer scan_;
  PassStats stats_{};
  std::int64_t start_counts_ = 0;
  std::vector<float> column_v_;                // column pass: sub-pixel row per column (NaN: none)
  std::vector<std::uint8_t> candidate_;        // rows the column pass re-reads
  std::vector<std::int16_t> row_lo_, row_hi_;  // and the columns it re-reads there
};

}  // namespace cellsight::algo
