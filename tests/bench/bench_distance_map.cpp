// Benchmark of algo/distance_map: transform + gradients of the full thesis grid, map memory, trilinear sampling.
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

using cellsight::algo::DistanceMap;
using cellsight::algo::DistanceMapView;
using cellsight::algo::EdtScratch;
using cellsight::algo::GradientMethod;
using cellsight::algo::GridDims;
using cellsight::algo::MapCell;
using cellsight::algo::MapSample;

using Clock = std::chrono::steady_clock;

double ms_since(Clock::time_point start) {
  return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

constexpr double kMiB = 1024.0 * 1024.0;
constexpr int kRepeats = 3;  // best of: the machine is shared

// A part-like template: a 0.45 x 0.9 m plate turned 20 deg about y and 8 deg about x, scanned in lines every 3 cells
// with 1-cell spacing along the line, with a round hole, plus 200 stray outlier cells. Returns the cell centres
// (grid coordinates) of what it marks, so the sampling benchmark can replay a scan against the map.
std::vector<Eigen::Vector3d> make_plate(const GridDims& d, std::vector<std::uint8_t>& occ) {
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
      if (s * s + (t - 50.0) * (t - 50.0) < 40.0 * 40.0) continue;
      mark(d.nx / 2.0 + s * std::cos(ay), d.ny / 2.0 + t * std::cos(ax),
           d.nz / 2.0 + s * std::sin(ay) + t * std::sin(ax));
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

// Gradient accuracy of both methods on one small 48^3 field, for the record (tests assert the bounds).
// truth(x, y, z, tx, ty) gives the true dD/dx, dD/dy at a cell, or false to leave the cell out.
template <class Truth>
void print_gradient_accuracy(const char* name, const std::vector<Eigen::Vector3i>& sites, Truth&& truth) {
  const GridDims d{48, 48, 48, 0.0022};
  std::vector<std::uint8_t> occ(d.cell_count(), 0);
  for (const auto& s : sites) occ[d.index(s.x(), s.y(), s.z())] = 1;
  EdtScratch scratch(d);
  std::vector<float> dist(d.cell_count());
  if (!cellsight::algo::edt_squared(occ.data(), d, scratch, dist.data()).ok()) return;
  cellsight::algo::distance_from_squared(d, dist.data());
  for (GradientMethod method : {GradientMethod::kSobelAveraged, GradientMethod::kCentralDifference}) {
    std::vector<float> gx(d.cell_count());
    std::vector<float> gy(d.cell_count());
    if (!cellsight::algo::gradients_xy(dist.data(), d, method, scratch, gx.data(), gy.data()).ok()) return;
    double sum2 = 0.0;
    double sum_angle2 = 0.0;
    double max_angle = 0.0;
    long n = 0;
    long n_angle = 0;
    for (int z = 1; z < d.nz - 1; ++z)
      for (int y = 1; y < d.ny - 1; ++y)
        for (int x = 1; x < d.nx - 1; ++x) {
          double tx = 0.0;
          double ty = 0.0;
          if (!truth(x, y, z, tx, ty)) continue;
          const std::size_t i = d.index(x, y, z);
          sum2 += (gx[i] - tx) * (gx[i] - tx) + (gy[i] - ty) * (gy[i] - ty);
          ++n;
          if (std::hypot(tx, ty) > 0.3) {
            const double a =
                std::abs(std::atan2(gx[i] * ty - gy[i] * tx, gx[i] * tx + gy[i] * ty)) * 180.0 / std::numbers::pi;
            sum_angle2 += a * a;
            max_angle = std::max(max_angle, a);
            ++n_angle;
          }
        }
    std::printf("  %-44s %-8s component rms %.5f   xy angle rms %.3f deg, max %.2f deg\n", name,
                method == GradientMethod::kSobelAveraged ? "sobel" : "central", std::sqrt(sum2 / n),
                std::sqrt(sum_angle2 / n_angle), max_angle);
  }
}

// Truth for a set of single cells: (p - q) / |p - q| for the unique nearest q; cells closer than 3 cells to a site,
// or whose second-nearest site is within 1.5 cells of the nearest (a ridge: no gradient there), are left out.
auto nearest_site_truth(const std::vector<Eigen::Vector3i>& sites) {
  return [&sites](int x, int y, int z, double& tx, double& ty) {
    double best = -1.0;
    double second = -1.0;
    Eigen::Vector3d q = Eigen::Vector3d::Zero();
    for (const auto& s : sites) {
      const double r = (Eigen::Vector3d(x, y, z) - s.cast<double>()).norm();
      if (best < 0.0 || r < best) {
        second = best;
        best = r;
        q = s.cast<double>();
      } else if (second < 0.0 || r < second) {
        second = r;
      }
    }
    if (best < 3.0 || (second >= 0.0 && second - best < 1.5)) return false;
    tx = (x - q.x()) / best;
    ty = (y - q.y()) / best;
    return true;
  };
}

void print_gradient_comparison() {
  std::printf("\ngradient accuracy, 48^3 grid, cells off the border:\n");
  std::printf(" against the exact gradient of the transform (cells >= 3 from a site, off ridges):\n");
  const std::vector<Eigen::Vector3i> one{Eigen::Vector3i(24, 24, 24)};
  print_gradient_accuracy("one point", one, nearest_site_truth(one));
  std::vector<Eigen::Vector3i> random_sites(40);
  std::mt19937 rng(1);
  std::uniform_int_distribution<int> site(0, 47);
  for (auto& s : random_sites) s = Eigen::Vector3i{site(rng), site(rng), site(rng)};
  print_gradient_accuracy("40 random points", random_sites, nearest_site_truth(random_sites));

  std::printf(" against the continuous surface that was voxelised (cells >= 3 from it; includes the staircase):\n");
  std::vector<Eigen::Vector3i> shell;
  constexpr double kRadius = 12.0;
  for (int z = 0; z < 48; ++z)
    for (int y = 0; y < 48; ++y)
      for (int x = 0; x < 48; ++x) {
        if (std::abs((Eigen::Vector3d(x, y, z) - Eigen::Vector3d(24, 24, 24)).norm() - kRadius) < 0.5) {
          shell.emplace_back(x, y, z);
        }
      }
  print_gradient_accuracy("sphere shell R = 12 cells, outside", shell, [](int x, int y, int z, double& tx, double& ty) {
    const Eigen::Vector3d p = Eigen::Vector3d(x, y, z) - Eigen::Vector3d(24, 24, 24);
    if (p.norm() < kRadius + 3.0) return false;
    tx = p.x() / p.norm();
    ty = p.y() / p.norm();
    return true;
  });
  // Plane z = 20 + 0.35 x + 0.2 y (cell coordinates), one occupied cell per (x, y) column.
  std::vector<Eigen::Vector3i> plane;
  for (int y = 0; y < 48; ++y)
    for (int x = 0; x < 48; ++x) {
      const int z = static_cast<int>(std::floor(20.0 + 0.35 * (x + 0.5) + 0.2 * (y + 0.5)));
      if (z < 48) plane.emplace_back(x, y, z);
    }
  print_gradient_accuracy("tilted plane, interior columns", plane, [](int x, int y, int z, double& tx, double& ty) {
    const Eigen::Vector3d normal = Eigen::Vector3d(-0.35, -0.2, 1.0).normalized();
    const double offset = ((z + 0.5) - (20.0 + 0.35 * (x + 0.5) + 0.2 * (y + 0.5))) * normal.z();
    // Stay where the nearest plane point has a voxel under it (the plane leaves the grid at z = 48).
    if (std::abs(offset) < 3.0 || x < 6 || y < 6 || x > 30 || y > 30) return false;
    const double side = offset > 0.0 ? 1.0 : -1.0;
    tx = side * normal.x();
    ty = side * normal.y();
    return true;
  });
}

// The same map in plain x-fastest order with the same arithmetic, inside the grid only: the reference that shows
// what the brick layout buys. It has no outside-the-grid term, so checksums differ when shifted points leave the grid.
class LinearReference {
 public:
  LinearReference(const DistanceMap& map, const Eigen::Vector3d& origin)
      : dims_(map.dims()), cells_(map.dims().cell_count()), inv_res_(1.0 / dims_.resolution_m) {
    const DistanceMapView view = map.view();
    for (int z = 0; z < dims_.nz; ++z)
      for (int y = 0; y < dims_.ny; ++y)
        for (int x = 0; x < dims_.nx; ++x) cells_[dims_.index(x, y, z)] = view.cell(x, y, z);
    for (int a = 0; a < 3; ++a) offset_[a] = origin[a] * inv_res_ + 0.5;
  }
  [[nodiscard]] MapSample sample(double x_m, double y_m, double z_m) const {
    const double f[3] = {x_m * inv_res_ - offset_[0], y_m * inv_res_ - offset_[1], z_m * inv_res_ - offset_[2]};
    const int n[3] = {dims_.nx, dims_.ny, dims_.nz};
    int lo[3];
    double t[3];
    for (int a = 0; a < 3; ++a) {
      const double c = std::clamp(f[a], 0.0, n[a] - 1.0);
      lo[a] = std::min(static_cast<int>(c), n[a] - 2);
      t[a] = c - lo[a];
    }
    const MapCell* p = cells_.data() + dims_.index(lo[0], lo[1], lo[2]);
    const std::ptrdiff_t sy = dims_.nx;
    const std::ptrdiff_t sz = static_cast<std::ptrdiff_t>(dims_.nx) * dims_.ny;
    const MapCell* corner[8] = {p, p + 1, p + sy, p + sy + 1, p + sz, p + sz + 1, p + sz + sy, p + sz + sy + 1};
    double w[8];
    for (int k = 0; k < 8; ++k) {
      w[k] =
          ((k & 1) != 0 ? t[0] : 1.0 - t[0]) * ((k & 2) != 0 ? t[1] : 1.0 - t[1]) * ((k & 4) != 0 ? t[2] : 1.0 - t[2]);
    }
    MapSample s{0.0, 0.0, 0.0};
    for (int k = 0; k < 8; ++k) {
      s.distance_m += w[k] * corner[k]->distance;
      s.grad_x += w[k] * corner[k]->grad_x;
      s.grad_y += w[k] * corner[k]->grad_y;
    }
    s.distance_m *= cellsight::algo::kDistanceUnitM;
    s.grad_x *= cellsight::algo::kGradientUnit;
    s.grad_y *= cellsight::algo::kGradientUnit;
    return s;
  }

 private:
  GridDims dims_;
  std::vector<MapCell> cells_;
  double inv_res_;
  double offset_[3] = {0.0, 0.0, 0.0};
};

}  // namespace

int main() {
  const GridDims d{296, 500, 182, 0.0022};
  const Eigen::Vector3d origin(-0.325, 0.0, -0.2);
  std::vector<std::uint8_t> occ(d.cell_count(), 0);
  const std::vector<Eigen::Vector3d> scan = make_plate(d, occ);
  long occupied = 0;
  for (std::uint8_t c : occ) occupied += c;
  std::printf("grid %d x %d x %d = %.1f M cells at %.1f mm, %ld occupied\n", d.nx, d.ny, d.nz, d.cell_count() / 1e6,
              d.resolution_m * 1e3, occupied);

  EdtScratch scratch(d);
  std::vector<float> work(d.cell_count());
  std::vector<float> gx(d.cell_count());
  std::vector<float> gy(d.cell_count());
  double edt_ms = 1e30;
  double sqrt_ms = 1e30;
  double sobel_ms = 1e30;
  double central_ms = 1e30;
  double build_ms = 1e30;
  DistanceMap map;
  for (int rep = 0; rep < kRepeats; ++rep) {
    auto t0 = Clock::now();
    if (!cellsight::algo::edt_squared(occ.data(), d, scratch, work.data()).ok()) return 1;
    edt_ms = std::min(edt_ms, ms_since(t0));
    t0 = Clock::now();
    cellsight::algo::distance_from_squared(d, work.data());
    sqrt_ms = std::min(sqrt_ms, ms_since(t0));
    t0 = Clock::now();
    if (!cellsight::algo::gradients_xy(work.data(), d, GradientMethod::kSobelAveraged, scratch, gx.data(), gy.data())
             .ok())
      return 1;
    sobel_ms = std::min(sobel_ms, ms_since(t0));
    t0 = Clock::now();
    if (!cellsight::algo::gradients_xy(work.data(), d, GradientMethod::kCentralDifference, scratch, gx.data(),
                                       gy.data())
             .ok())
      return 1;
    central_ms = std::min(central_ms, ms_since(t0));
    t0 = Clock::now();
    if (!cellsight::algo::build_distance_map(occ.data(), d, origin, GradientMethod::kCentralDifference, scratch,
                                             work.data(), map)
             .ok())
      return 1;
    build_ms = std::min(build_ms, ms_since(t0));
  }
  std::printf("\nteach-time build, best of %d, one thread:\n", kRepeats);
  std::printf("  edt_squared (3 passes)            %8.1f ms\n", edt_ms);
  std::printf("  sqrt pass                         %8.1f ms\n", sqrt_ms);
  std::printf("  gradients, Sobel averaged (float) %8.1f ms\n", sobel_ms);
  std::printf("  gradients, central diff (float)   %8.1f ms\n", central_ms);
  std::printf("  build_distance_map (all, compact) %8.1f ms\n", build_ms);

  // Precision of the compact map against the float field (work holds the float distances, gx/gy the central ones).
  double worst_d = 0.0;
  double worst_g = 0.0;
  const DistanceMapView view = map.view();
  for (std::size_t i = 0; i < d.cell_count(); ++i) {
    const auto& c =
        view.cell(static_cast<int>(i % d.nx), static_cast<int>(i / d.nx % d.ny), static_cast<int>(i / d.nx / d.ny));
    worst_d = std::max(worst_d, std::abs(c.distance * cellsight::algo::kDistanceUnitM - work[i]));
    worst_g = std::max({worst_g, std::abs(c.grad_x * cellsight::algo::kGradientUnit - gx[i]),
                        std::abs(c.grad_y * cellsight::algo::kGradientUnit - gy[i])});
  }
  std::printf("\nmemory:\n");
  std::printf("  compact map (uint16 distance + 2 x int16 gradient) %7.1f MiB  (6 bytes/cell, %.1f %% brick padding)\n",
              map.memory_bytes() / kMiB, 100.0 * (static_cast<double>(map.cells().size()) / d.cell_count() - 1.0));
  std::printf("  same as three float maps                          %7.1f MiB\n", 3.0 * 4.0 * d.cell_count() / kMiB);
  std::printf("  teach-time float work volume                      %7.1f MiB (+ %.2f MiB scratch)\n",
              4.0 * d.cell_count() / kMiB, (4.0 * scratch.line_f.size() * 4 + 4.0 * scratch.plane.size()) / kMiB);
  std::printf("  compact vs float: max distance error %.4f mm, max gradient error %.2e\n", worst_d * 1e3, worst_g);

  // Sampling, 1e6 samples each: (a) uniformly random in the grid box: every sample a fresh part of the 157 MiB map;
  // (b) all scan points, shifted by a small pose, in scan order; (c) Perfect Match's pattern: 2000 points spread over
  // the part, visited again and again while the pose moves a little (500 "iterations").
  constexpr int kSamples = 1000000;
  std::vector<Eigen::Vector3d> random_points(kSamples);
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> ux(origin.x(), origin.x() + d.nx * d.resolution_m);
  std::uniform_real_distribution<double> uy(origin.y(), origin.y() + d.ny * d.resolution_m);
  std::uniform_real_distribution<double> uz(origin.z(), origin.z() + d.nz * d.resolution_m);
  for (auto& p : random_points) p = Eigen::Vector3d{ux(rng), uy(rng), uz(rng)};
  const auto posed = [&](const Eigen::Vector3d& cell, double theta_rad, double dx_cells, double dy_cells) {
    const double x = cell.x() - d.nx / 2.0;
    const double y = cell.y() - d.ny / 2.0;
    return Eigen::Vector3d(
        origin +
        d.resolution_m * Eigen::Vector3d(d.nx / 2.0 + std::cos(theta_rad) * x - std::sin(theta_rad) * y + dx_cells,
                                         d.ny / 2.0 + std::sin(theta_rad) * x + std::cos(theta_rad) * y + dy_cells,
                                         cell.z()));
  };
  std::vector<Eigen::Vector3d> scan_points(kSamples);
  for (int i = 0; i < kSamples; ++i) {
    scan_points[static_cast<std::size_t>(i)] =
        posed(scan[static_cast<std::size_t>(i) % scan.size()], 1.5 * std::numbers::pi / 180.0, 2.3, -1.7);
  }
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
  const LinearReference linear(map, origin);
  std::printf("\n1e6 trilinear samples, best of %d (ns per sample):\n", kRepeats);
  std::printf("  %-44s %12s %12s\n", "", "brick layout", "x-fastest");
  const std::pair<const char*, const std::vector<Eigen::Vector3d>*> sets[] = {
      {"random in the grid box", &random_points},
      {"all scan points in scan order", &scan_points},
      {"2000 points x 500 iterations (PM pattern)", &pm_points}};
  for (const auto& [name, set] : sets) {
    double best_ns[2] = {1e30, 1e30};
    double checksum[2] = {0.0, 0.0};
    for (int rep = 0; rep < kRepeats; ++rep) {
      for (int layout = 0; layout < 2; ++layout) {
        double sum = 0.0;
        const auto t0 = Clock::now();
        for (const Eigen::Vector3d& p : *set) {
          const MapSample s = layout == 0 ? view.sample(p.x(), p.y(), p.z()) : linear.sample(p.x(), p.y(), p.z());
          sum += s.distance_m + s.grad_x + s.grad_y;
        }
        best_ns[layout] = std::min(best_ns[layout], ms_since(t0) * 1e6 / static_cast<double>(set->size()));
        checksum[layout] = sum;
      }
    }
    std::printf("  %-44s %12.1f %12.1f   (checksums %.3f %.3f)\n", name, best_ns[0], best_ns[1], checksum[0],
                checksum[1]);
  }
  print_gradient_comparison();
  return 0;
}
