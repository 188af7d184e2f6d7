// Benchmark of algo/distance_map: transform of the full thesis grid, sparse map build and memory, sampling speed.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <numbers>
#include <random>
#include <utility>
#include <vector>

#include "algo/distance_map.hpp"

namespace {

using cellsight::algo::BrickGrid;
using cellsight::algo::DistanceMap;
using cellsight::algo::DistanceMapView;
using cellsight::algo::EdtScratch;
using cellsight::algo::GridDims;
using cellsight::algo::kFineFar;
using cellsight::algo::MapSample;

using Clock = std::chrono::steady_clock;

double ms_since(Clock::time_point start) {
  return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

constexpr double kMiB = 1024.0 * 1024.0;
constexpr int kRepeats = 3;  // best of: the machine is shared

// A part-like template: a 0.45 x 0.9 m plate turned 20 deg about y and 8 deg about x, scanned in lines every 3 cells
// with 1-cell spacing along the line, with a round hole and a relief (a wave up to 12 cells high over a third of the
// plate, like ribs on a pressed part), plus 200 stray outlier cells. Returns the cell-space points it marks, so the
// sampling benchmark can replay a scan against the map.
std::vector<Eigen::Vector3d> make_part(const GridDims& d, std::vector<std::uint8_t>& occ) {
  std::vector<Eigen::Vector3d> points;
  const double ay = 20.0 * std::numbers::pi / 180.0;
  const double ax = 8.0 * std::numbers::pi / 180.0;
  const auto mark = [&](double fx, double fy, double fz) {
    const int x = static_cast<int>(std::floor(fx));
    const int y = static_cast<int>(std::floor(fy));
    const int z = static_cast<int>(std::floor(fz));
    if (x < 0 || y < 0 || z < 0 || x >= d.nx || y >= d.ny || z >= d.nz) return;
    occ[d.index(x, y, z)] = 1;
    points.emplace_back(fx, fy, fz);
  };
  const double half_w = 0.45 / d.resolution_m / 2.0;
  const double half_h = 0.9 / d.resolution_m / 2.0;
  for (int line = 0; line <= static_cast<int>(2.0 * half_h / 3.0); ++line) {
    for (int step = 0; step <= static_cast<int>(2.0 * half_w); ++step) {
      const double t = -half_h + 3.0 * line;
      const double s = -half_w + step;
      if (s * s + (t - 50.0) * (t - 50.0) < 40.0 * 40.0) continue;  // hole
      const double relief = t > half_h / 3.0 ? 6.0 * (1.0 - std::cos(s / 8.0)) : 0.0;
      mark(d.nx / 2.0 + s * std::cos(ay), d.ny / 2.0 + t * std::cos(ax),
           d.nz / 2.0 + s * std::sin(ay) + t * std::sin(ax) + relief);
    }
  }
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> ux(0.0, d.nx);
  std::uniform_real_distribution<double> uy(0.0, d.ny);
  std::uniform_real_distribution<double> uz(0.0, d.nz);
  for (int i = 0; i < 200; ++i) {
    const Eigen::Vector3d p{ux(rng), uy(rng), uz(rng)};  // braces: drawn in this order
    mark(p.x(), p.y(), p.z());
  }
  return points;
}

// Share of points whose 8 interpolation corners are all fine (sample() takes the fine path), for the record.
double fine_share(const DistanceMapView& view, const std::vector<Eigen::Vector3d>& points_m) {
  const GridDims& d = view.dims();
  const int n[3] = {d.nx, d.ny, d.nz};
  long fine = 0;
  for (const Eigen::Vector3d& p : points_m) {
    int lo[3];
    for (int a = 0; a < 3; ++a) {
      const double c = std::clamp((p[a] - view.origin_m()[a]) / d.resolution_m - 0.5, 0.0, n[a] - 1.0);
      lo[a] = std::min(static_cast<int>(c), std::max(n[a] - 2, 0));
    }
    bool all = true;
    for (int k = 0; k < 8; ++k) {
      all = all && view.fine(std::min(lo[0] + (k & 1), n[0] - 1), std::min(lo[1] + ((k >> 1) & 1), n[1] - 1),
                             std::min(lo[2] + ((k >> 2) & 1), n[2] - 1)) != kFineFar;
    }
    fine += all ? 1 : 0;
  }
  return 100.0 * static_cast<double>(fine) / static_cast<double>(points_m.size());
}

}  // namespace

int main() {
  const GridDims d{296, 500, 182, 0.0022};
  const Eigen::Vector3d origin(-0.325, 0.0, -0.2);
  std::vector<std::uint8_t> occ(d.cell_count(), 0);
  const std::vector<Eigen::Vector3d> scan = make_part(d, occ);
  long occupied = 0;
  for (std::uint8_t c : occ) occupied += c;
  const BrickGrid grid(d);
  std::printf("grid %d x %d x %d = %.1f M cells at %.1f mm, %ld occupied; %zu bricks of 8^3 (%d x %d x %d)\n", d.nx,
              d.ny, d.nz, d.cell_count() / 1e6, d.resolution_m * 1e3, occupied, grid.brick_count(), grid.count(0),
              grid.count(1), grid.count(2));

  EdtScratch scratch(d);
  std::vector<float> work(d.cell_count());
  double edt_ms = 1e30;
  double sqrt_ms = 1e30;
  for (int rep = 0; rep < kRepeats; ++rep) {
    auto t0 = Clock::now();
    if (!cellsight::algo::edt_squared(occ.data(), d, scratch, work.data()).ok()) return 1;
    edt_ms = std::min(edt_ms, ms_since(t0));
    t0 = Clock::now();
    cellsight::algo::distance_from_squared(d, work.data());
    sqrt_ms = std::min(sqrt_ms, ms_since(t0));
  }
  std::printf("\nteach time, best of %d, one thread:\n", kRepeats);
  std::printf("  edt_squared (3 passes)               %8.1f ms\n", edt_ms);
  std::printf("  sqrt pass                            %8.1f ms\n", sqrt_ms);

  // Build (transform + band selection + quantization) for three bands; the default 17.6 mm map is kept for sampling.
  const double bands_m[] = {0.0088, cellsight::algo::kDefaultBandM, cellsight::algo::kMaxFineDistanceM};
  DistanceMap maps[3];
  for (int i = 0; i < 3; ++i) {
    double build_ms = 1e30;
    for (int rep = 0; rep < kRepeats; ++rep) {
      const auto t0 = Clock::now();
      const auto status =
          cellsight::algo::build_distance_map(occ.data(), d, origin, bands_m[i], scratch, work.data(), maps[i]);
      if (!status.ok()) {
        std::printf("build failed: %s\n", status.error().message.c_str());
        return 1;
      }
      build_ms = std::min(build_ms, ms_since(t0));
    }
    std::printf("  build_distance_map, band %4.1f mm     %8.1f ms (transform and sqrt included)\n", bands_m[i] * 1e3,
                build_ms);
  }

  std::printf("\nmemory of the sparse map (table + coarse: %.2f MiB for every band):\n",
              2.0 * 2.0 * static_cast<double>(grid.brick_count()) / kMiB);
  std::printf("  %-10s %14s %10s %12s %12s\n", "band", "stored bricks", "of all", "fine MiB", "total MiB");
  for (int i = 0; i < 3; ++i) {
    const DistanceMap& m = maps[i];
    std::printf("  %5.1f mm   %14zu %9.1f%% %12.2f %12.2f\n", bands_m[i] * 1e3, m.stored_bricks(),
                100.0 * static_cast<double>(m.stored_bricks()) / static_cast<double>(grid.brick_count()),
                static_cast<double>(m.bricks().size()) / kMiB, static_cast<double>(m.memory_bytes()) / kMiB);
  }
  std::printf("  for scale: full grid at 6 bytes/cell (version 1) %.1f MiB, teach-time float volume %.1f MiB\n",
              6.0 * static_cast<double>(d.cell_count()) / kMiB, 4.0 * static_cast<double>(d.cell_count()) / kMiB);

  // Sampling, 1e6 samples each, on the default-band map: (a) Perfect Match's pattern: 2000 scan points spread over the
  // part, visited again and again while the pose converges (500 iterations), all near the surface; (b) uniformly
  // random in the grid box, mostly the coarse field.
  constexpr int kSamples = 1000000;
  const auto posed = [&](const Eigen::Vector3d& cell, double theta_rad, double dx_cells, double dy_cells) {
    const double x = cell.x() - d.nx / 2.0;
    const double y = cell.y() - d.ny / 2.0;
    return Eigen::Vector3d(
        origin +
        d.resolution_m * Eigen::Vector3d(d.nx / 2.0 + std::cos(theta_rad) * x - std::sin(theta_rad) * y + dx_cells,
                                         d.ny / 2.0 + std::sin(theta_rad) * x + std::cos(theta_rad) * y + dy_cells,
                                         cell.z()));
  };
  std::vector<Eigen::Vector3d> pm_points;
  pm_points.reserve(kSamples);
  constexpr int kPmPoints = 2000;
  const std::size_t pm_step = scan.size() / kPmPoints;
  for (int iteration = 0; static_cast<int>(pm_points.size()) < kSamples; ++iteration) {
    const double k = 1.0 - iteration / 500.0;  // pose converging from (3 deg, 5, -4 cells) to 0
    for (int j = 0; j < kPmPoints && static_cast<int>(pm_points.size()) < kSamples; ++j) {
      pm_points.push_back(
          posed(scan[static_cast<std::size_t>(j) * pm_step], k * 3.0 * std::numbers::pi / 180.0, k * 5.0, k * -4.0));
    }
  }
  std::vector<Eigen::Vector3d> random_points(kSamples);
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> ux(origin.x(), origin.x() + d.nx * d.resolution_m);
  std::uniform_real_distribution<double> uy(origin.y(), origin.y() + d.ny * d.resolution_m);
  std::uniform_real_distribution<double> uz(origin.z(), origin.z() + d.nz * d.resolution_m);
  for (auto& p : random_points) p = Eigen::Vector3d{ux(rng), uy(rng), uz(rng)};

  const DistanceMapView view = maps[1].view();
  std::printf("\n1e6 samples on the %.1f mm map, best of %d:\n", bands_m[1] * 1e3, kRepeats);
  std::printf("  %-44s %10s %12s\n", "", "ns/sample", "fine path");
  const std::pair<const char*, const std::vector<Eigen::Vector3d>*> sets[] = {
      {"near the surface (2000 points x 500 PM iter.)", &pm_points},
      {"uniformly random in the grid box", &random_points}};
  for (const auto& [name, set] : sets) {
    double best_ns = 1e30;
    double checksum = 0.0;
    for (int rep = 0; rep < kRepeats; ++rep) {
      double sum = 0.0;
      const auto t0 = Clock::now();
      for (const Eigen::Vector3d& p : *set) {
        const MapSample s = view.sample(p.x(), p.y(), p.z());
        sum += s.distance_m + s.grad_x + s.grad_y;
      }
      best_ns = std::min(best_ns, ms_since(t0) * 1e6 / static_cast<double>(set->size()));
      checksum = sum;
    }
    std::printf("  %-44s %10.1f %11.1f%%   (checksum %.3f)\n", name, best_ns, fine_share(view, *set), checksum);
  }
  return 0;
}
