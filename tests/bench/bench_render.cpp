// Benchmark: simulated-cell frame rendering, 1024x768 on one core (target >= 500 frames/s).
#include <time.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <opencv2/core/utility.hpp>
#include <vector>

#include "app/config.hpp"
#include "app/sim_setup.hpp"

// Thread CPU time: the figure stays meaningful when other work shares the machine (wall time would not).
double cpu_ms() {
  timespec t{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return static_cast<double>(t.tv_sec) * 1e3 + static_cast<double>(t.tv_nsec) * 1e-6;
}

int main() {
  cv::setNumThreads(1);  // one core: OpenCV's resize must not fan out
  auto config = cellsight::app::load_config(CELLSIGHT_SOURCE_DIR "/config/cellsight.yaml");
  if (!config) {
    std::fprintf(stderr, "%s\n", config.error().message.c_str());
    return 1;
  }
  auto cell = cellsight::app::make_sim_cell(*config);
  if (!cell) {
    std::fprintf(stderr, "%s\n", cell.error().message.c_str());
    return 1;
  }
  cv::Mat image;
  std::printf("%-20s %8s %10s %10s %10s\n", "part", "frames", "median_ms", "p95_ms", "frames/s");
  std::vector<double> all_ms;
  for (const auto& part : cell->catalogue()) {
    auto pass = cell->random_pass(part.name, 7);
    if (!pass || !cell->begin_pass(*pass)) return 1;
    std::vector<double> ms;
    for (int i = 0; i < cell->frame_count(); ++i) {
      const double t0 = cpu_ms();
      cell->render_frame(i, config->camera.exposure_us, image);
      ms.push_back(cpu_ms() - t0);
    }
    all_ms.insert(all_ms.end(), ms.begin(), ms.end());
    std::sort(ms.begin(), ms.end());
    double total = 0;
    for (double v : ms) total += v;
    std::printf("%-20s %8zu %10.3f %10.3f %10.0f\n", part.name.c_str(), ms.size(), ms[ms.size() / 2],
                ms[ms.size() * 95 / 100], 1000.0 * static_cast<double>(ms.size()) / total);
  }
  std::sort(all_ms.begin(), all_ms.end());
  double total = 0;
  for (double v : all_ms) total += v;
  std::printf(
      "ALL %zu frames %dx%d: median %.3f ms, p95 %.3f ms, max %.3f ms, mean rate %.0f frames/s (one core, thread CPU "
      "time)\n",
      all_ms.size(), image.cols, image.rows, all_ms[all_ms.size() / 2], all_ms[all_ms.size() * 95 / 100], all_ms.back(),
      1000.0 * static_cast<double>(all_ms.size()) / total);
  return 0;
}
