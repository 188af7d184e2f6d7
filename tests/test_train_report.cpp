// The training report of `cellsight train` (folder, summary, YAML, plots) and its progress line, checked against a
// hand-built training report whose truth (per-scan predictions) the test keeps on its own.
#include <stdio.h>  // open_memstream
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <catch2/catch.hpp>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <limits>
#include <opencv2/imgcodecs.hpp>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "app/train_progress.hpp"
#include "app/train_report.hpp"
#include "app/train_report_plots.hpp"
#include "tests/scratch_dir.hpp"

using namespace cellsight;
namespace fs = std::filesystem;

namespace {

using test::TempDir;

std::string read_text(const fs::path& file) {
  std::ifstream in(file, std::ios::binary);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

std::vector<std::string> entries(const fs::path& dir) {
  std::vector<std::string> names;
  for (const auto& e : fs::directory_iterator(dir)) names.push_back(e.path().filename().string());
  std::sort(names.begin(), names.end());
  return names;
}

// The line of `text` that starts with `prefix` (empty when none).
std::string line_starting(const std::string& text, const std::string& prefix) {
  std::istringstream in(text);
  std::string line;
  while (std::getline(in, line)) {
    if (line.rfind(prefix, 0) == 0) return line;
  }
  return {};
}

struct Prediction {
  int truth, predicted;
};

// The test's own truth: one entry per test scan.
struct HandReport {
  std::vector<std::string> names = {"bracket_a", "bracket_b", "door_panel_l", "hood"};
  std::vector<Prediction> svm_predictions, knn_predictions;
  algo::TrainingReport report;
};

std::vector<Prediction> predictions_from(const std::vector<std::vector<int>>& counts) {
  std::vector<Prediction> p;
  for (std::size_t t = 0; t < counts.size(); ++t) {
    for (std::size_t c = 0; c < counts[t].size(); ++c) {
      for (int n = 0; n < counts[t][c]; ++n) p.push_back({static_cast<int>(t), static_cast<int>(c)});
    }
  }
  return p;
}

std::vector<std::vector<int>> confusion_of(const std::vector<Prediction>& predictions, int classes) {
  std::vector<std::vector<int>> m(static_cast<std::size_t>(classes),
                                  std::vector<int>(static_cast<std::size_t>(classes)));
  for (const Prediction& p : predictions) ++m[static_cast<std::size_t>(p.truth)][static_cast<std::size_t>(p.predicted)];
  return m;
}

double accuracy_of(const std::vector<Prediction>& predictions) {
  int ok = 0;
  for (const Prediction& p : predictions) ok += p.truth == p.predicted ? 1 : 0;
  return static_cast<double>(ok) / static_cast<double>(predictions.size());
}

// An annealing run of `steps` steps: T0 = 200 cooled by 0.95 (thesis 6.4.2), Metropolis acceptance on the error in
// percentage points, candidates drawn at random.
std::vector<algo::AnnealingStep> make_curve(int steps, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> acc(0.80, 0.99), unit(0.0, 1.0);
  std::uniform_int_distribution<int> active(8, 30);
  std::vector<algo::AnnealingStep> curve;
  double t = 200.0, current = 0.85, best = 0.85;
  curve.push_back({0, t, current, current, best, 15, true});
  for (int i = 1; i <= steps; ++i) {
    const double candidate = acc(rng);
    const bool accept = candidate >= current || unit(rng) < std::exp(-100.0 * (current - candidate) / t);
    if (accept) current = candidate;
    best = std::max(best, current);
    curve.push_back({i, t, candidate, current, best, active(rng), accept});
    t *= 0.95;
  }
  return curve;
}

HandReport make_hand_report() {
  HandReport h;
  // 15 test scans per part: bracket_b is taken for door_panel_l three times, the others rarely err.
  h.svm_predictions = predictions_from({{15, 0, 0, 0}, {0, 12, 3, 0}, {0, 1, 13, 1}, {1, 0, 0, 14}});
  h.knn_predictions = predictions_from({{13, 2, 0, 0}, {4, 9, 2, 0}, {0, 3, 12, 0}, {0, 0, 1, 14}});
  algo::TrainingReport& r = h.report;
  r.class_names = h.names;
  r.train_samples = 140;
  r.test_samples = static_cast<int>(h.svm_predictions.size());
  r.folds = 5;
  r.threads = 2;
  r.seconds = 171.4;
  r.svm.classifier = algo::Classifier::kSvm;
  r.svm_hyper.kernel = algo::KernelType::kRbf;
  r.svm_hyper.c = 4.0;
  r.svm_hyper.gamma_factor = 10.0;
  const std::vector<int> chosen = {0, 1, 3, 9, 20, 33, 41, 62, 63, 70, 71, 73};
  for (int f : chosen) {
    r.svm.mask.set(static_cast<std::size_t>(f));
    r.svm.features.emplace_back(algo::feature_name(f));
  }
  r.svm.parameters = r.svm_hyper.describe(static_cast<int>(chosen.size()));
  r.svm.cv_accuracy = 0.975;
  r.svm.confusion = confusion_of(h.svm_predictions, 4);
  r.svm.test_accuracy = accuracy_of(h.svm_predictions);
  r.svm.curve = make_curve(60, 7);
  r.svm.evaluations = 55;
  r.svm.cache_hits = 6;
  r.svm.seconds = 150.2;
  algo::ClassifierReport knn;
  knn.classifier = algo::Classifier::kKnn;
  knn.parameters = "k=3 (Euclidean, majority vote)";
  knn.cv_accuracy = 0.86;
  knn.confusion = confusion_of(h.knn_predictions, 4);
  knn.test_accuracy = accuracy_of(h.knn_predictions);
  knn.features = {"width_m", "height_m", "area_m2"};
  knn.curve = make_curve(30, 8);
  knn.seconds = 12.0;
  r.knn = knn;
  return h;
}

app::TrainReportContext make_context() {
  app::TrainReportContext c;
  c.model_db_path = "models/";
  c.dataset = "simulated catalogue, 4 parts x 50 scans";
  c.date = "2025-01-31 14:05:09";
  c.planned_iterations = 200;
  return c;
}

// Any pixel within `radius` of p whose colour is within `tolerance` (sum of channel differences) of `color`.
bool colour_near(const cv::Mat& image, cv::Point2d p, const cv::Scalar& color, int radius = 2, int tolerance = 60) {
  const int cx = static_cast<int>(std::lround(p.x)), cy = static_cast<int>(std::lround(p.y));
  for (int y = cy - radius; y <= cy + radius; ++y) {
    for (int x = cx - radius; x <= cx + radius; ++x) {
      if (x < 0 || y < 0 || x >= image.cols || y >= image.rows) continue;
      const cv::Vec3b& v = image.at<cv::Vec3b>(y, x);
      const int d = std::abs(v[0] - static_cast<int>(color[0])) + std::abs(v[1] - static_cast<int>(color[1])) +
                    std::abs(v[2] - static_cast<int>(color[2]));
      if (d <= tolerance) return true;
    }
  }
  return false;
}

// Width of the pixels in `cell` that differ from the cell's fill (the printed count), 0 when none.
int ink_width(const cv::Mat& image, const cv::Rect& cell, int min_difference) {
  const cv::Vec3b& fill = image.at<cv::Vec3b>(cell.y + 3, cell.x + 3);
  int lo = std::numeric_limits<int>::max(), hi = -1;
  for (int y = cell.y + 2; y < cell.y + cell.height - 2; ++y) {
    for (int x = cell.x + 2; x < cell.x + cell.width - 2; ++x) {
      const cv::Vec3b& v = image.at<cv::Vec3b>(y, x);
      const int d = std::abs(v[0] - fill[0]) + std::abs(v[1] - fill[1]) + std::abs(v[2] - fill[2]);
      if (d >= min_difference) {
        lo = std::min(lo, x);
        hi = std::max(hi, x);
      }
    }
  }
  return hi < 0 ? 0 : hi - lo + 1;
}

}  // namespace

SCENARIO("A training report is written as a folder of text, YAML and readable plots", "[train_report]") {
  const HandReport h = make_hand_report();
  TempDir tmp;
  GIVEN("a report with SVM and kNN and a folder that does not exist yet") {
    const fs::path dir = tmp.path() / "report";
    auto written = app::write_training_report(dir.string(), h.report, make_context());
    REQUIRE(written.ok());
    THEN("every file is there, nothing for the absent MLP, and no staging folder is left behind") {
      CHECK(*written == dir.string());
      CHECK(entries(dir) == std::vector<std::string>{"annealing_knn.csv", "annealing_knn.png", "annealing_svm.csv",
                                                     "annealing_svm.png", "confusion_knn.png", "confusion_svm.png",
                                                     "report.yaml", "summary.txt"});
      CHECK(entries(tmp.path()) == std::vector<std::string>{"report"});
    }
    THEN("the folder and its files are readable by everyone, as a report should be") {
      const fs::perms others = fs::perms::others_read;
      CHECK((fs::status(dir).permissions() & others) == others);
      CHECK((fs::status(dir).permissions() & fs::perms::others_exec) == fs::perms::others_exec);
      CHECK((fs::status(dir / "summary.txt").permissions() & others) == others);
    }
    THEN("the PNGs load with sensible sizes") {
      for (const char* name : {"confusion_svm.png", "confusion_knn.png"}) {
        const cv::Mat image = cv::imread((dir / name).string(), cv::IMREAD_COLOR);
        REQUIRE_FALSE(image.empty());
        CHECK(image.cols >= 4 * 34);  // four cells of at least 34 px, plus names
        CHECK(image.rows >= 4 * 34);
        CHECK(image.cols <= 1600);
        CHECK(image.rows <= 1600);
        CHECK(image.rows == app::render_confusion_image(h.names, h.report.svm.confusion, "x").rows);
      }
      for (const char* name : {"annealing_svm.png", "annealing_knn.png"}) {
        const cv::Mat image = cv::imread((dir / name).string(), cv::IMREAD_COLOR);
        REQUIRE_FALSE(image.empty());
        CHECK(image.cols == 1000);
        CHECK(image.rows == 720);
      }
    }
    THEN("the CSV has a header and one line per annealing step") {
      const std::string csv = read_text(dir / "annealing_svm.csv");
      CHECK(static_cast<std::size_t>(std::count(csv.begin(), csv.end(), '\n')) == h.report.svm.curve.size() + 1);
      CHECK(csv.rfind("iteration,temperature,candidate_accuracy,", 0) == 0);
    }
  }
}

SCENARIO("The summary states the figures of the report, checked against the test's own count", "[train_report]") {
  const HandReport h = make_hand_report();
  const std::string text = app::training_summary_text(h.report, make_context());
  INFO(text);
  // Independent truth from the per-scan predictions.
  int correct = 0;
  std::vector<int> per_class_total(4, 0), per_class_correct(4, 0);
  for (const Prediction& p : h.svm_predictions) {
    ++per_class_total[static_cast<std::size_t>(p.truth)];
    if (p.truth == p.predicted) {
      ++correct;
      ++per_class_correct[static_cast<std::size_t>(p.truth)];
    }
  }
  WHEN("the layout is looked at") {
    THEN("no line is wider than 100 columns, so it reads in a terminal and prints on A4") {
      std::istringstream in(text);
      for (std::string line; std::getline(in, line);) {
        INFO(line);
        CHECK(line.size() <= 100);
      }
    }
  }
  WHEN("the headline figures are read") {
    THEN("test accuracy, the scan counts, CV accuracy and the verdict are right") {
      char expected[128];
      std::snprintf(expected, sizeof expected, "%.1f %%  (%d of %d scans)", 100.0 * correct / 60.0, correct, 60);
      CHECK(line_starting(text, "Test accuracy (held-back scans):").find(expected) != std::string::npos);
      CHECK(line_starting(text, "Cross-validation accuracy (5-fold").find("97.5 %") != std::string::npos);
      CHECK(line_starting(text, "Scans:").find("140 for training, 60 held back for the test (15 per class)") !=
            std::string::npos);
      // 54 of 60 = 90 %: below the 97 % target.
      CHECK(line_starting(text, "RESULT: LOW") != "");
      CHECK(line_starting(text, "Date:").find("2025-01-31 14:05:09") != std::string::npos);
      CHECK(line_starting(text, "Model database:").find("models/") != std::string::npos);
    }
    THEN("the kernel line gives C and gamma = i / active features") {
      const std::string kernel = line_starting(text, "Kernel:");
      CHECK(kernel.find("RBF") != std::string::npos);
      CHECK(kernel.find("C = 4,") != std::string::npos);
      CHECK(kernel.find("gamma = 0.8333") != std::string::npos);  // 10 / 12
      CHECK(kernel.find("i = 10 over 12") != std::string::npos);
    }
    THEN("the number and the names of the chosen features are listed") {
      CHECK(line_starting(text, "Chosen features (12 of 74):") != "");
      for (const std::string& f : h.report.svm.features) CHECK(text.find(f) != std::string::npos);
    }
  }
  WHEN("the per-class table is read") {
    THEN("each part's test scans, correct scans and recall equal the count from the predictions") {
      for (std::size_t c = 0; c < 4; ++c) {
        const std::string line = line_starting(text, "  " + h.names[c] + " ");
        REQUIRE(line != "");
        std::istringstream in(line);
        std::string name;
        int total = -1, ok = -1;
        double recall = -1.0;
        in >> name >> total >> ok >> recall;
        CHECK(name == h.names[c]);
        CHECK(total == per_class_total[c]);
        CHECK(ok == per_class_correct[c]);
        CHECK(recall == Approx(100.0 * per_class_correct[c] / per_class_total[c]).margin(0.05));
      }
    }
  }
  WHEN("the confusions are read") {
    THEN("the worst comes first with its count and share") {
      const std::string worst = line_starting(text, "  bracket_b -> door_panel_l:");
      CHECK(worst == "  bracket_b -> door_panel_l: 3 of 15 scans (20.0 %)");
      const auto header = text.find("Worst confusions on the test split");
      REQUIRE(header != std::string::npos);
      const auto first = text.find('\n', header) + 1;
      CHECK(text.compare(first, worst.size(), worst) == 0);
      CHECK(text.find("hood -> bracket_a: 1 of 15 scans (6.7 %)") != std::string::npos);
    }
  }
  WHEN("the comparison, the time and the advice are read") {
    THEN("kNN is compared, the run was not stopped, and the advice names the worst pair") {
      const std::string knn = line_starting(text, "  kNN");
      char knn_acc[32];
      std::snprintf(knn_acc, sizeof knn_acc, "%.1f %%", 100.0 * accuracy_of(h.knn_predictions));
      CHECK(knn.find(knn_acc) != std::string::npos);
      CHECK(knn.find("86.0 %") != std::string::npos);
      CHECK(line_starting(text, "    kNN: k=3 (Euclidean, majority vote)") != "");
      CHECK(line_starting(text, "  MLP") == "");
      CHECK(line_starting(text, "Time:").find("2 min 51 s") != std::string::npos);
      CHECK(line_starting(text, "Stopped early: no") != "");
      CHECK(text.find("(here bracket_b and door_panel_l)") != std::string::npos);
      // CV 97.5 % vs test 90 %: the gap advice applies.
      CHECK(text.find("a gap this large") != std::string::npos);
    }
  }
}

SCENARIO("The summary of a good run and of a stopped run", "[train_report]") {
  HandReport h = make_hand_report();
  GIVEN("a perfect SVM") {
    h.report.svm.confusion = {{15, 0, 0, 0}, {0, 15, 0, 0}, {0, 0, 15, 0}, {0, 0, 0, 15}};
    h.report.svm.test_accuracy = 1.0;
    const std::string text = app::training_summary_text(h.report, make_context());
    THEN("the verdict is OK and there are no confusions") {
      CHECK(line_starting(text, "RESULT: OK - SVM test accuracy 100.0 %") != "");
      CHECK(text.find("none: every test scan was recognised as its own part.") != std::string::npos);
      CHECK(text.find("It is not low now") != std::string::npos);
    }
  }
  GIVEN("no scans held back for the test") {
    h.report.test_samples = 0;
    h.report.svm.test_accuracy = std::numeric_limits<double>::quiet_NaN();
    h.report.svm.confusion.assign(4, std::vector<int>(4, 0));
    const std::string text = app::training_summary_text(h.report, make_context());
    THEN("no verdict and no recall is claimed") {
      CHECK(line_starting(text, "RESULT: UNKNOWN") != "");
      CHECK(line_starting(text, "Test accuracy (held-back scans):   n/a") == "Test accuracy (held-back scans):   n/a");
      CHECK(line_starting(text, "Scans:").find("no scans held back for the test") != std::string::npos);
      CHECK(line_starting(text, "  hood ").find("n/a (no test scans)") != std::string::npos);
    }
  }
  GIVEN("an SVM annealing stopped by Ctrl-C after 57 of 200 steps, without comparison") {
    h.report.svm.curve = make_curve(57, 3);
    h.report.svm.stopped = true;
    h.report.stopped = true;
    h.report.knn.reset();
    const std::string text = app::training_summary_text(h.report, make_context());
    THEN("the summary says so and advises to run it to the end") {
      CHECK(line_starting(text, "WARNING: the training was stopped early") != "");
      CHECK(line_starting(text, "Stopped early: YES - after 57 of 200 SVM annealing steps") != "");
      CHECK(text.find("run it again to the end") != std::string::npos);
      CHECK(text.find("Comparison") == std::string::npos);
    }
  }
}

SCENARIO("report.yaml carries the same numbers", "[train_report]") {
  const HandReport h = make_hand_report();
  const YAML::Node y = YAML::Load(app::training_report_yaml(h.report, make_context()));
  THEN("classes, hyper-parameters, confusion, recall and curve match the report") {
    CHECK(y["format_version"].as<int>() == 1);
    CHECK(y["classes"].as<std::vector<std::string>>() == h.names);
    CHECK(y["test_samples"].as<int>() == 60);
    CHECK(y["svm_hyper"]["kernel"].as<std::string>() == "rbf");
    CHECK(y["svm_hyper"]["c"].as<double>() == 4.0);
    CHECK(y["svm_hyper"]["gamma"].as<double>() == Approx(10.0 / 12.0));
    const YAML::Node svm = y["classifiers"]["svm"];
    CHECK(svm["test_accuracy"].as<double>() == Approx(accuracy_of(h.svm_predictions)));
    CHECK(svm["features"].as<std::vector<std::string>>() == h.report.svm.features);
    CHECK(svm["confusion"].as<std::vector<std::vector<int>>>() == confusion_of(h.svm_predictions, 4));
    CHECK(svm["per_class_recall"]["bracket_b"].as<double>() == Approx(12.0 / 15.0));
    const YAML::Node rows = svm["curve"]["rows"];
    REQUIRE(rows.size() == h.report.svm.curve.size());
    for (std::size_t i = 0; i < rows.size(); ++i) {
      const algo::AnnealingStep& s = h.report.svm.curve[i];
      CHECK(rows[i][0].as<int>() == s.iteration);
      CHECK(rows[i][1].as<double>() == Approx(s.temperature).epsilon(1e-7));
      CHECK(rows[i][2].as<double>() == Approx(s.candidate_accuracy).epsilon(1e-7));
      CHECK(rows[i][4].as<double>() == Approx(s.best_accuracy).epsilon(1e-7));
      CHECK(rows[i][6].as<bool>() == s.accepted);
    }
    CHECK(y["classifiers"]["knn"]["confusion"].as<std::vector<std::vector<int>>>() == h.report.knn->confusion);
    CHECK_FALSE(y["classifiers"]["mlp"]);
  }
}

SCENARIO("The confusion image shades each cell by its share and prints every count", "[train_report]") {
  const HandReport h = make_hand_report();
  app::ConfusionLayout layout;
  const cv::Mat image = app::render_confusion_image(h.names, h.report.svm.confusion, "SVM", &layout);
  const auto& m = h.report.svm.confusion;
  REQUIRE(layout.cell_px >= 34);
  THEN("empty cells are white, right answers green, wrong ones red, darker for a larger share of the row") {
    for (int i = 0; i < 4; ++i) {
      for (int j = 0; j < 4; ++j) {
        const cv::Rect r = layout.cell(i, j);
        const cv::Vec3b& fill = image.at<cv::Vec3b>(r.y + 3, r.x + 3);
        INFO("cell " << i << "," << j << " fill " << fill);
        const int count = m[static_cast<std::size_t>(i)][static_cast<std::size_t>(j)];
        if (count == 0) {
          CHECK((fill[0] >= 250 && fill[1] >= 250 && fill[2] >= 250));
        } else if (i == j) {
          CHECK(fill[1] > fill[0] + 10);
          CHECK(fill[1] > fill[2] + 10);
        } else {
          CHECK(fill[2] > fill[0] + 20);
          CHECK(fill[2] > fill[1] + 20);
        }
      }
    }
    auto brightness = [&](int i, int j) {
      const cv::Rect r = layout.cell(i, j);
      const cv::Vec3b& v = image.at<cv::Vec3b>(r.y + 3, r.x + 3);
      return v[0] + v[1] + v[2];
    };
    // Diagonal shares 15/15 > 14/15 > 13/15 > 12/15: darker in that order.
    CHECK(brightness(0, 0) < brightness(3, 3));
    CHECK(brightness(3, 3) < brightness(2, 2));
    CHECK(brightness(2, 2) < brightness(1, 1));
    // Errors: 3/15 darker than 1/15.
    CHECK(brightness(1, 2) < brightness(3, 0));
  }
  THEN("every cell holds its count: two digits print wider than one, zeros faintly") {
    // Black or white ink differs from its fill by 400+ (sum over channels); the light grey of a zero by ~180.
    const int two_digits = ink_width(image, layout.cell(0, 0), 250);
    const int one_digit = ink_width(image, layout.cell(1, 2), 250);
    const int zero_strong = ink_width(image, layout.cell(0, 1), 250);
    const int zero_faint = ink_width(image, layout.cell(0, 1), 40);
    CHECK(one_digit > 3);
    CHECK(two_digits > one_digit + 4);
    CHECK(zero_strong == 0);  // zero is printed in light grey, not black
    CHECK(zero_faint > 3);
  }
}

SCENARIO("The annealing plot draws the curve where its axes say", "[train_report]") {
  const HandReport h = make_hand_report();
  const auto& curve = h.report.svm.curve;
  app::AnnealingPlotLayout layout;
  const cv::Mat image = app::render_annealing_image(h.report.svm, "SVM", &layout);
  THEN("the axes cover every value") {
    double lo = 1.0;
    for (const auto& s : curve) lo = std::min({lo, s.candidate_accuracy, s.current_accuracy});
    CHECK(layout.accuracy.y_min <= 100.0 * lo);
    CHECK(layout.accuracy.y_max >= 100.0);
    CHECK(layout.accuracy.x_max == Approx(60.0));
    CHECK(layout.temperature.y_min <= curve.back().temperature);
    CHECK(layout.temperature.y_max >= 200.0);
    CHECK(layout.temperature.log_y);
  }
  THEN("best line, candidates and temperature appear at their data coordinates") {
    const auto& last = curve.back();
    CHECK(colour_near(image, layout.accuracy.to_px(last.iteration, 100.0 * last.best_accuracy), app::kBestLineColor));
    CHECK(colour_near(image, layout.temperature.to_px(0, 200.0), app::kTemperatureLineColor));
    CHECK(colour_near(image, layout.temperature.to_px(last.iteration, last.temperature), app::kTemperatureLineColor));
    int rejected_checked = 0, accepted_checked = 0;
    for (const auto& s : curve) {
      // Only candidates well away from the lines drawn over them, so a line cannot be what is seen.
      // Dots are drawn over the current line and under the best line.
      const cv::Point2d p = layout.accuracy.to_px(s.iteration, 100.0 * s.candidate_accuracy);
      const double to_current = std::abs(p.y - layout.accuracy.to_px(s.iteration, 100.0 * s.current_accuracy).y);
      const double to_best = std::abs(p.y - layout.accuracy.to_px(s.iteration, 100.0 * s.best_accuracy).y);
      if (to_best < 8.0 || (!s.accepted && to_current < 8.0)) continue;
      if (s.accepted) {
        CHECK(colour_near(image, p, app::kAcceptedPointColor, 1));
        ++accepted_checked;
      } else {
        CHECK(colour_near(image, p + cv::Point2d(3, 0), app::kRejectedPointColor, 1, 90));  // on the ring
        ++rejected_checked;
      }
    }
    CHECK(rejected_checked > 2);
    CHECK(accepted_checked > 0);
  }
  THEN("the legend names what is drawn") {
    // The legend row sits above the panel; each of its sample marks uses the plot colours.
    int found = 0;
    for (const app::Bgr& c : {app::kBestLineColor, app::kCurrentLineColor, app::kAcceptedPointColor}) {
      bool hit = false;
      for (int x = layout.accuracy.area.x; x < layout.accuracy.area.x + layout.accuracy.area.width && !hit; ++x) {
        hit = colour_near(image, {static_cast<double>(x), layout.accuracy.area.y - 14.0}, c, 0, 40);
      }
      found += hit ? 1 : 0;
    }
    CHECK(found == 3);
  }
}

SCENARIO("An existing folder with something in it is never overwritten", "[train_report]") {
  const HandReport h = make_hand_report();
  TempDir tmp;
  const fs::path dir = tmp.path() / "reports";
  fs::create_directory(dir);
  { std::ofstream(dir / "keep.txt") << "earlier report"; }
  GIVEN("the refusing policy") {
    app::TrainReportContext c = make_context();
    c.if_not_empty = app::ExistingReportDir::kRefuse;
    auto written = app::write_training_report(dir.string(), h.report, c);
    THEN("a clear error, and the folder holds exactly what it held") {
      REQUIRE_FALSE(written.ok());
      CHECK(written.error().message.find("nothing was written") != std::string::npos);
      CHECK(entries(dir) == std::vector<std::string>{"keep.txt"});
      CHECK(read_text(dir / "keep.txt") == "earlier report");
    }
  }
  GIVEN("the default policy, twice") {
    auto first = app::write_training_report(dir.string(), h.report, make_context());
    auto second = app::write_training_report(dir.string(), h.report, make_context());
    THEN("two new dated subfolders, the old file untouched") {
      REQUIRE(first.ok());
      REQUIRE(second.ok());
      CHECK(*first == (dir / "report-2025-01-31_140509").string());
      CHECK(*second == (dir / "report-2025-01-31_140509-2").string());
      CHECK(entries(dir) ==
            std::vector<std::string>{"keep.txt", "report-2025-01-31_140509", "report-2025-01-31_140509-2"});
      CHECK(read_text(dir / "keep.txt") == "earlier report");
      CHECK(fs::exists(fs::path(*second) / "summary.txt"));
    }
  }
  GIVEN("a path that is a file") {
    auto written = app::write_training_report((dir / "keep.txt").string(), h.report, make_context());
    THEN("refused") {
      REQUIRE_FALSE(written.ok());
      CHECK(written.error().message.find("not a folder") != std::string::npos);
      CHECK(read_text(dir / "keep.txt") == "earlier report");
    }
  }
  GIVEN("an empty existing folder, named with a trailing slash") {
    const fs::path empty = tmp.path() / "empty";
    fs::create_directory(empty);
    auto written = app::write_training_report(empty.string() + "/", h.report, make_context());
    THEN("the report goes straight into it") {
      REQUIRE(written.ok());
      CHECK(fs::exists(empty / "summary.txt"));
      CHECK(entries(tmp.path()) == std::vector<std::string>{"empty", "reports"});
    }
  }
  GIVEN("a folder whose parent does not exist") {
    auto written = app::write_training_report((tmp.path() / "missing" / "report").string(), h.report, make_context());
    THEN("refused, nothing created") {
      REQUIRE_FALSE(written.ok());
      CHECK(written.error().message.find("does not exist") != std::string::npos);
      CHECK_FALSE(fs::exists(tmp.path() / "missing"));
    }
  }
  GIVEN("a report whose confusion matrix does not fit its classes") {
    algo::TrainingReport bad = h.report;
    bad.svm.confusion.pop_back();
    auto written = app::write_training_report((tmp.path() / "bad").string(), bad, make_context());
    THEN("refused before anything is created") {
      REQUIRE_FALSE(written.ok());
      CHECK(written.error().message.find("confusion matrix has 3 rows for 4 classes") != std::string::npos);
      CHECK_FALSE(fs::exists(tmp.path() / "bad"));
    }
  }
}

SCENARIO("Durations and the progress line", "[train_report][progress]") {
  THEN("elapsed time is truncated, ETA rounded up, hours appear past 59:59") {
    CHECK(app::format_duration(0.0, false) == "0:00");
    CHECK(app::format_duration(59.9, false) == "0:59");
    CHECK(app::format_duration(59.9, true) == "1:00");
    CHECK(app::format_duration(83.0, false) == "1:23");
    CHECK(app::format_duration(83.0, true) == "1:23");
    CHECK(app::format_duration(0.2, true) == "0:01");
    CHECK(app::format_duration(3599.0, false) == "59:59");
    CHECK(app::format_duration(3600.0, false) == "1:00:00");
    CHECK(app::format_duration(3723.2, true) == "1:02:04");
    CHECK(app::format_duration(-1.0, false) == "--:--");
    CHECK(app::format_duration(std::numeric_limits<double>::quiet_NaN(), true) == "--:--");
    CHECK(app::format_duration(std::numeric_limits<double>::infinity(), true) == "--:--");
  }
  GIVEN("step 90 of 200 of a single-stage SVM run") {
    algo::TrainingProgress p;
    p.iteration = 90;
    p.iterations = 200;
    p.best_accuracy = 0.98312;
    p.best_active = 17;
    p.elapsed_s = 83.4;
    // As train_recogniser computes it: mean step time times the steps left.
    p.eta_s = 83.4 / 90 * (200 - 90);  // 101.93 s
    THEN("bar, counter, best, elapsed and ETA read right") {
      CHECK(app::format_progress(p) ==
            "SVM [#########...........]  90/200  45%  best 98.3 % (17 features)  elapsed 1:23  ETA 1:42");
    }
  }
  GIVEN("the kNN stage (2 of 3), before and at its end") {
    algo::TrainingProgress p;
    p.classifier = algo::Classifier::kKnn;
    p.stage = 1;
    p.stages = 3;
    p.iterations = 50;
    p.iteration = 0;
    p.elapsed_s = 4000.0;
    const std::string start = app::format_progress(p);
    p.iteration = 50;
    p.eta_s = 0.0;
    const std::string end = app::format_progress(p);
    THEN("the stage is named, ETA unknown at the start and zero at the end") {
      CHECK(start.rfind("kNN 2/3 [....................]  0/50   0%", 0) == 0);
      CHECK(start.find("elapsed 1:06:40  ETA --:--") != std::string::npos);
      CHECK(end.rfind("kNN 2/3 [####################] 50/50 100%", 0) == 0);
      CHECK(end.find("ETA 0:00") != std::string::npos);
    }
  }
}

namespace {

// Captures what a ProgressPrinter writes.
class Capture {
 public:
  Capture() : file_(open_memstream(&data_, &size_)) { REQUIRE(file_ != nullptr); }
  ~Capture() {
    close();
    std::free(data_);
  }
  Capture(const Capture&) = delete;
  Capture& operator=(const Capture&) = delete;
  [[nodiscard]] std::FILE* file() const { return file_; }
  std::string text() {
    close();
    return std::string(data_, size_);
  }

 private:
  void close() {
    if (file_ != nullptr) std::fclose(file_);
    file_ = nullptr;
  }
  char* data_ = nullptr;
  std::size_t size_ = 0;
  std::FILE* file_;
};

algo::TrainingProgress step(int stage, int stages, int iteration, int iterations, double elapsed_s, double eta_s) {
  algo::TrainingProgress p;
  p.classifier = stage == 0 ? algo::Classifier::kSvm : algo::Classifier::kKnn;
  p.stage = stage;
  p.stages = stages;
  p.iteration = iteration;
  p.iterations = iterations;
  p.best_accuracy = 0.9;
  p.best_active = 12;
  p.elapsed_s = elapsed_s;
  p.eta_s = eta_s;
  return p;
}

}  // namespace

SCENARIO("The progress printer writes log lines off a terminal and redraws one line on it",
         "[train_report][progress]") {
  GIVEN("a log stream, 10 s interval, two stages of 30 one-second steps") {
    Capture out;
    std::vector<std::string> expected;
    {
      app::ProgressPrinter printer(out.file(), false, 10.0);
      for (int stage = 0; stage < 2; ++stage) {
        for (int it = 1; it <= 30; ++it) {
          const auto p = step(stage, 2, it, 30, stage * 30.0 + it, 30.0 - it);
          printer.update(p);
          // First and last step of a stage, and 10 s after the last line: steps 1, 11, 21, 30.
          if (it == 1 || it == 11 || it == 21 || it == 30) expected.push_back(app::format_progress(p));
        }
      }
      CHECK(printer.prints() == 8);
    }
    THEN("one full line each time, no carriage returns") {
      const std::string text = out.text();
      CHECK(text.find('\r') == std::string::npos);
      std::vector<std::string> lines;
      std::istringstream in(text);
      for (std::string line; std::getline(in, line);) lines.push_back(line);
      CHECK(lines == expected);
    }
  }
  GIVEN("a terminal, updates every 0.05 s, a stage that ends and one stopped midway") {
    Capture out;
    std::string last_of_first, last_of_second;
    int updates = 0;
    {
      app::ProgressPrinter printer(out.file(), true);
      for (int it = 1; it <= 20; ++it) {
        const auto p = step(0, 2, it, 20, 0.05 * it, 0.05 * (20 - it));
        printer.update(p);
        ++updates;
        last_of_first = app::format_progress(p);
      }
      for (int it = 1; it <= 7; ++it) {
        const auto p = step(1, 2, it, 20, 1.0 + 0.05 * it, 0.05 * (20 - it));
        printer.update(p);
        ++updates;
        if (it == 7) last_of_second = app::format_progress(p);
      }
      // Redraws at most every 0.1 s: fewer than the updates, more than one per stage.
      CHECK(printer.prints() < updates);
      CHECK(printer.prints() > 4);
      printer.finish();
    }
    THEN("each stage ends on its own line, showing its last state, redraws in between") {
      const std::string text = out.text();
      CHECK(std::count(text.begin(), text.end(), '\n') == 2);
      const auto first_end = text.find('\n');
      const auto first_start = text.rfind('\r', first_end);
      CHECK(text.substr(first_start + 1, first_end - first_start - 1) == last_of_first);
      const auto second_end = text.find('\n', first_end + 1);
      const auto second_start = text.rfind('\r', second_end);
      CHECK(text.substr(second_start + 1, second_end - second_start - 1) == last_of_second);
      CHECK(std::count(text.begin(), text.end(), '\r') > 4);
    }
  }
  GIVEN("a terminal 40 columns wide") {
    Capture out;
    const auto p = step(0, 1, 5, 100, 5.0, 95.0);
    { app::ProgressPrinter(out.file(), true, 10.0, 40).update(p); }
    THEN("the line is cut to 39 columns so it cannot wrap") {
      CHECK(out.text() == "\r" + app::format_progress(p).substr(0, 39) + "\n");
    }
  }
  GIVEN("a terminal line that gets shorter (ETA from 1:00:00 to 59:59)") {
    Capture out;
    std::string shorter;
    {
      app::ProgressPrinter printer(out.file(), true);
      printer.update(step(0, 1, 1, 100, 1.0, 3600.0));
      const auto p = step(0, 1, 2, 100, 2.0, 3599.0);
      shorter = app::format_progress(p);
      printer.update(p);
    }
    THEN("the redraw rubs out the old tail with spaces, and the destructor ends the line") {
      const std::string text = out.text();
      const auto second = text.rfind('\r');
      CHECK(text.substr(second + 1) == shorter + "  \n");
    }
  }
}
