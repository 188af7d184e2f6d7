// Benchmark of formats/template_file on the full default grid (296 x 500 x 182): build, write, open (mmap + header
// checks) and body verification, cold (file evicted from the page cache) and warm. Prints figures; not registered.
// Usage: bench_template_file [FOLDER [keep]] (default: the system temp folder; keep: leave the file there)
#include <fcntl.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

#include "formats/template_file.hpp"

namespace {

using Clock = std::chrono::steady_clock;
double ms_since(Clock::time_point t) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t).count();
}

// A 0.5 x 0.7 m sheet tilted in depth with two holes and a bent flange, sampled every 1 mm, centred in the grid.
std::vector<cellsight::algo::ScanPoint> sheet_part(const cellsight::algo::GridSpec& g) {
  std::vector<cellsight::algo::ScanPoint> pts;
  const double x0 = g.origin_m.x() + 0.075, y0 = g.origin_m.y() + 0.2, z0 = g.origin_m.z() + 0.15;
  constexpr double kStep = 0.001;
  for (int i = 0; i <= 500; ++i) {
    const double u = i * kStep;
    for (int j = 0; j <= 700; ++j) {
      const double v = j * kStep;
      if (std::hypot(u - 0.15, v - 0.5) < 0.05 || std::hypot(u - 0.35, v - 0.2) < 0.08) continue;
      pts.push_back({static_cast<float>(x0 + u), static_cast<float>(y0 + v), static_cast<float>(z0 + 0.1 * u), 0, 0});
    }
    for (int k = 0; k <= 80; ++k) {
      const double w = k * kStep;
      pts.push_back({static_cast<float>(x0 + u), static_cast<float>(y0), static_cast<float>(z0 + 0.1 * u + w), 0, 0});
    }
  }
  return pts;
}

bool evict(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return false;
  const bool ok = ::posix_fadvise(fd, 0, 0, POSIX_FADV_DONTNEED) == 0;
  ::close(fd);
  return ok;
}

}  // namespace

int main(int argc, char** argv) {
  namespace fs = std::filesystem;
  const fs::path folder = argc > 1 ? fs::path(argv[1]) : fs::temp_directory_path();
  const std::string path = (folder / "bench_template_file.dmap").string();
  const cellsight::algo::GridSpec grid;  // defaults: the thesis grid
  const auto pts = sheet_part(grid);
  std::printf("grid %s, %zu points\n", cellsight::formats::describe_grid(grid).c_str(), pts.size());

  for (const double band_m : {0.0088, cellsight::algo::kDefaultBandM, cellsight::algo::kMaxFineDistanceM}) {
    cellsight::formats::TemplateBuildParams params;
    params.band_m = band_m;
    auto t = Clock::now();
    auto model = cellsight::formats::build_template(pts, grid, params);
    const double build_ms = ms_since(t);
    if (!model) {
      std::fprintf(stderr, "%s\n", model.error().message.c_str());
      return 1;
    }
    std::printf(
        "build (band %.1f mm): %.0f ms, %zu occupied cells, %zu surface cells, %zu of %zu bricks stored, "
        "map %.2f MB\n",
        band_m * 1e3, build_ms, model->occupied_cells, model->surface_cells.size(), model->map.stored_bricks(),
        model->map.brick_table().size(), static_cast<double>(model->map.memory_bytes()) / 1e6);
  }

  {
    const auto model = cellsight::formats::build_template(pts, grid);
    const auto t = Clock::now();
    if (auto w = cellsight::formats::write_template(path, *model, {"bench-sheet", 1, 0}); !w) {
      std::fprintf(stderr, "%s\n", w.error().message.c_str());
      return 1;
    }
    std::printf("write (streamed, fsync'ed): %.0f ms, file %.1f MB (%ju bytes)\n", ms_since(t),
                static_cast<double>(fs::file_size(path)) / 1e6, static_cast<std::uintmax_t>(fs::file_size(path)));
  }  // releases the in-memory map

  auto t = Clock::now();
  const auto info = cellsight::formats::read_template_info(path);
  std::printf("header only (read_template_info): %.3f ms (%s)\n", ms_since(t), info ? "ok" : "failed");

  for (int run = 0; run < 6; ++run) {
    const bool cold = run < 3;
    if (cold && !evict(path)) std::printf("(could not evict the file from the page cache)\n");
    t = Clock::now();
    const auto file = cellsight::formats::TemplateFile::open(path, grid);
    const double total_ms = ms_since(t);
    if (!file) {
      std::fprintf(stderr, "%s\n", file.error().message.c_str());
      return 1;
    }
    const double mb = static_cast<double>(file->info().file_bytes) / 1e6;
    std::printf("open %s: read + header checks %.3f ms, body verify %.0f ms (%.2f GB/s), total %.0f ms\n",
                cold ? "cold" : "warm", file->load_timing().read_ms, file->load_timing().verify_ms,
                mb / file->load_timing().verify_ms, total_ms);
  }
  if (!(argc > 2 && std::string(argv[2]) == "keep")) fs::remove(path);
  return 0;
}
