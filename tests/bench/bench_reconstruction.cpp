// Benchmark: per-frame reconstruction on one core — stripe extraction, and triangulation + accumulation into the
// scan buffer — on frames of a simulated pass (budgets: 0.5 ms and 0.2 ms per 1024x768 frame).
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <vector>

#include "../sim_test_util.hpp"
#include "algo/scan_builder.hpp"
#include "app/config.hpp"
#include "app/scan_acquisition.hpp"
#include "app/sim_setup.hpp"

using Clock = std::chrono::steady_clock;
using namespace cellsight;

int main() {
  auto cfg = app::load_config(CELLSIGHT_SOURCE_DIR "/config/cellsight.yaml");
  auto cell = app::make_sim_cell(*cfg);
  if (!cfg || !cell) return 1;
  const algo::ScanBuilderParams params = app::scan_builder_params(*cfg);
  algo::ScanBuilder builder(params, test::true_calibration(cell->rig()));
  std::vector<double> stripe_ms, total_ms;
  std::size_t points = 0;
  double total_s = 0;
  for (const char* part : {"ribbed_v4", "louvred_panel", "tray", "perforated_fine"}) {
    auto pass = cell->random_pass(part, 3);
    if (!pass || !cell->begin_pass(*pass)) return 1;
    std::vector<cv::Mat> frames(static_cast<std::size_t>(cell->frame_count()));
    for (int i = 0; i < cell->frame_count(); ++i)
      cell->render_frame(i, cfg->camera.exposure_us, frames[static_cast<std::size_t>(i)]);
    builder.begin_pass(0, static_cast<std::int32_t>(cfg->camera.exposure_us));
    for (int i = 0; i < cell->frame_count(); ++i) {
      const cv::Mat& f = frames[static_cast<std::size_t>(i)];
      const auto t1 = Clock::now();
      const algo::FrameOutcome out =
          builder.add_frame(f.data, f.cols, f.rows, static_cast<int>(f.step),
                            static_cast<std::int32_t>(cfg->camera.exposure_us), cell->frame_info(i).encoder_counts);
      const auto t2 = Clock::now();
      total_ms.push_back(std::chrono::duration<double, std::milli>(t2 - t1).count());
      total_s += std::chrono::duration<double>(t2 - t1).count();
      points += static_cast<std::size_t>(out.points_added);
    }
    // Stripe extraction alone on the same frames.
    algo::StripeProfile profile(frames[0].rows);
    for (const cv::Mat& f : frames) {
      const auto t0 = Clock::now();
      (void)algo::extract_stripe(f.data, f.cols, f.rows, static_cast<int>(f.step), params.stripe, profile);
      stripe_ms.push_back(std::chrono::duration<double, std::milli>(Clock::now() - t0).count());
    }
  }
  auto median = [](std::vector<double> v) {
    std::sort(v.begin(), v.end());
    return v[v.size() / 2];
  };
  const double stripe = median(stripe_ms), whole = median(total_ms);
  std::printf("frames %zu (1024x768)\n", total_ms.size());
  std::printf("stripe extraction:              median %.3f ms/frame\n", stripe);
  std::printf("stripe + exposure + triangulation + accumulation: median %.3f ms/frame\n", whole);
  std::printf("triangulation + accumulation (difference): %.3f ms/frame\n", whole - stripe);
  const double per_frame = static_cast<double>(points) / static_cast<double>(total_ms.size());
  std::printf(
      "reconstructed points: %zu (%.0f per frame); %.2f M points/s through the whole per-frame path, "
      "%.1f M points/s for triangulation + accumulation alone\n",
      points, per_frame, static_cast<double>(points) / total_s / 1e6, per_frame / std::max(1e-9, whole - stripe) / 1e3);
  return 0;
}
