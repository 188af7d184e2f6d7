// Benchmark of algo/stripe: ms per 1024x768 mono8 frame on one core (median over 300 realistic frames).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <ctime>
#include <random>
#include <vector>

#include "algo/stripe.hpp"

namespace {

using cellsight::algo::StripeKernel;

constexpr int kWidth = 1024;
constexpr int kHeight = 768;
constexpr int kFrames = 8;  // distinct frames, cycled (rendering is not timed)
constexpr int kRuns = 300;  // timed extractions per configuration

// A frame like the simulated cell's: ambient 4-10 DN with read noise ~2 DN and hot pixels, a meandering stripe
// (sigma 0.8-1.6 px, peak around saturation with blooming, shot noise), 10 % of rows without part, ghost runs
// beside the stripe and saturated specular blobs.
std::vector<std::uint8_t> render(std::uint32_t seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> n01(0.0, 1.0);
  std::uniform_real_distribution<double> u01(0.0, 1.0);
  std::vector<std::uint8_t> img(std::size_t(kWidth) * kHeight);
  const double ambient = 4.0 + 6.0 * u01(rng);
  const double phase = 6.28 * u01(rng);
  const int hole_begin = int(u01(rng) * (kHeight - 80));
  const int ghost_begin = int(u01(rng) * (kHeight - 60));
  const int spike_row = int(u01(rng) * (kHeight - 5));
  for (int r = 0; r < kHeight; ++r) {
    std::uint8_t* row = img.data() + std::size_t(r) * kWidth;
    std::vector<double> v(kWidth);
    for (int x = 0; x < kWidth; ++x) {
      v[std::size_t(x)] = ambient + 2.0 * n01(rng);
    }
    const bool hole = r >= hole_begin && r < hole_begin + 77;
    if (!hole) {
      const double c = 300.0 + 150.0 * std::sin(0.01 * r + phase) + 0.1 * r;
      const double peak = 320.0 * (1.0 + 0.5 * std::sin(0.03 * r));
      const double sigma = (0.8 + 0.8 * u01(rng)) * (1.0 + 0.15 * std::log(std::max(1.0, peak / 255.0)));
      auto add_line = [&](double centre, double amplitude) {
        for (int x = std::max(0, int(centre) - 12); x < std::min(kWidth, int(centre) + 13); ++x) {
          const double d = (x - centre) / sigma;
          v[std::size_t(x)] += amplitude * std::exp(-0.5 * d * d);
        }
      };
      add_line(c, peak);
      if (r >= ghost_begin && r < ghost_begin + 50) {
        add_line(c + 25.0, 0.6 * peak);
      }
      if (r >= spike_row && r < spike_row + 4) {
        add_line(c - 40.0, 3000.0);
      }
    }
    for (int x = 0; x < kWidth; ++x) {
      const double s = v[std::size_t(x)];
      const double noisy = s + std::sqrt(std::max(0.0, s - ambient) / 16.0) * n01(rng);
      row[x] = std::uint8_t(std::clamp(std::lround(noisy), 0L, 255L));
    }
    if (u01(rng) < 0.05) {
      row[std::size_t(u01(rng) * (kWidth - 1))] = 255;  // hot pixel
    }
  }
  return img;
}

double thread_cpu_ms() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return double(ts.tv_sec) * 1e3 + double(ts.tv_nsec) * 1e-6;
}

struct Timing {
  double wall_ms = 0.0;  // median wall time
  double cpu_ms = 0.0;   // median on-CPU time of this thread: robust when other jobs share the cores
};

double median(std::vector<double>& v) {
  std::nth_element(v.begin(), v.begin() + std::ptrdiff_t(v.size() / 2), v.end());
  return v[v.size() / 2];
}

Timing time_frames(const std::vector<std::vector<std::uint8_t>>& frames, StripeKernel kernel,
                   cellsight::algo::StripeProfile& profile, int* valid_rows) {
  const cellsight::algo::StripeParams params;
  std::vector<double> wall, cpu;
  wall.reserve(kRuns);
  cpu.reserve(kRuns);
  for (int i = 0; i < kRuns; ++i) {
    const auto& img = frames[std::size_t(i) % frames.size()];
    const double c0 = thread_cpu_ms();
    const auto t0 = std::chrono::steady_clock::now();
    const auto result = cellsight::algo::extract_stripe(img.data(), kWidth, kHeight, kWidth, params, profile, kernel);
    const auto t1 = std::chrono::steady_clock::now();
    const double c1 = thread_cpu_ms();
    if (result != cellsight::algo::StripeResult::kOk) {
      std::fprintf(stderr, "extract_stripe failed: %s\n", cellsight::algo::to_string(result));
      return {};
    }
    *valid_rows = profile.summary().valid_rows;
    wall.push_back(std::chrono::duration<double, std::milli>(t1 - t0).count());
    cpu.push_back(c1 - c0);
  }
  return {median(wall), median(cpu)};
}

void print(const char* what, const Timing& t) {
  std::printf("  %-28s wall %.3f ms  cpu %.3f ms/frame  -> %6.0f frames/s (cpu)\n", what, t.wall_ms, t.cpu_ms,
              1000.0 / t.cpu_ms);
}

}  // namespace

int main() {
  std::vector<std::vector<std::uint8_t>> frames;
  for (int i = 0; i < kFrames; ++i) {
    frames.push_back(render(std::uint32_t(1000 + i)));
  }
  const std::vector<std::vector<std::uint8_t>> dark(1, std::vector<std::uint8_t>(std::size_t(kWidth) * kHeight, 6));
  cellsight::algo::StripeProfile profile(kHeight);
  int valid = 0;
  std::printf("bench_stripe: %dx%d mono8, median of %d frames, one core, budget 0.5 ms (DESIGN.md)\n", kWidth, kHeight,
              kRuns);
  std::printf("  vector kernel: %s\n", cellsight::algo::stripe_has_simd() ? "SSE2" : "none (scalar build)");
  const Timing best = time_frames(frames, StripeKernel::kBest, profile, &valid);
  print("stripe frames, best kernel:", best);
  std::printf("  (%d of %d rows valid; the rest are the rendered hole)\n", valid, kHeight);
  print("stripe frames, scalar kernel:", time_frames(frames, StripeKernel::kScalar, profile, &valid));
  print("empty frame, best kernel:", time_frames(dark, StripeKernel::kBest, profile, &valid));
  return 0;
}
