// The training report for programs: report.yaml (every figure of the summary and more) and the annealing curve as CSV.
#include <yaml-cpp/yaml.h>

#include <cmath>
#include <string>
#include <vector>

#include "app/train_report.hpp"
#include "base/local_time.hpp"
#include "base/string_printf.hpp"

namespace cellsight::app {
namespace {

using base::string_printf;

constexpr int kReportFormatVersion = 1;

}  // namespace

namespace {

void emit_number(YAML::Emitter& out, double v) {
  if (std::isfinite(v)) {
    out << v;
  } else {
    out << YAML::Null;
  }
}

void emit_classifier(YAML::Emitter& out, const algo::ClassifierReport& r, const std::vector<std::string>& names) {
  out << YAML::BeginMap;
  out << YAML::Key << "parameters" << YAML::Value << r.parameters;
  out << YAML::Key << "test_accuracy" << YAML::Value;
  emit_number(out, r.test_accuracy);
  out << YAML::Key << "cv_accuracy" << YAML::Value;
  emit_number(out, r.cv_accuracy);
  if (r.classifier == algo::Classifier::kSvm) {
    out << YAML::Key << "test_top2" << YAML::Value;
    emit_number(out, r.test_top2);
    out << YAML::Key << "test_ece" << YAML::Value;
    emit_number(out, r.test_ece);
    out << YAML::Key << "reliability" << YAML::Value << YAML::BeginSeq;
    for (const algo::CalibrationBin& b : r.reliability) {
      out << YAML::Flow
          << std::vector<double>{b.lo, b.hi, static_cast<double>(b.scans), b.mean_probability, b.accuracy};
    }
    out << YAML::EndSeq;
  }
  out << YAML::Key << "active_features" << YAML::Value << active_feature_count(r);
  out << YAML::Key << "features" << YAML::Value << YAML::Flow << r.features;
  out << YAML::Key << "evaluations" << YAML::Value << r.evaluations;
  out << YAML::Key << "cache_hits" << YAML::Value << r.cache_hits;
  out << YAML::Key << "seconds" << YAML::Value << r.seconds;
  out << YAML::Key << "stopped" << YAML::Value << r.stopped;
  const std::vector<double> recall = per_class_recall(r.confusion);
  out << YAML::Key << "per_class_recall" << YAML::Value << YAML::BeginMap;
  for (std::size_t i = 0; i < names.size() && i < recall.size(); ++i) {
    out << YAML::Key << names[i] << YAML::Value;
    emit_number(out, recall[i]);
  }
  out << YAML::EndMap;
  out << YAML::Key << "confusion" << YAML::Value << YAML::BeginSeq;
  for (const auto& row : r.confusion) out << YAML::Flow << row;
  out << YAML::EndSeq;
  out << YAML::Key << "curve" << YAML::Value << YAML::BeginMap;
  out << YAML::Key << "columns" << YAML::Value << YAML::Flow
      << std::vector<std::string>{"iteration",        "temperature",   "candidate_accuracy",
                                  "current_accuracy", "best_accuracy", "candidate_active",
                                  "accepted"};
  out << YAML::Key << "rows" << YAML::Value << YAML::BeginSeq;
  for (const algo::AnnealingStep& st : r.curve) {
    out << YAML::Flow << YAML::BeginSeq << st.iteration << st.temperature << st.candidate_accuracy
        << st.current_accuracy << st.best_accuracy << st.candidate_active << st.accepted << YAML::EndSeq;
  }
  out << YAML::EndSeq << YAML::EndMap;
  out << YAML::EndMap;
}

}  // namespace

std::string training_report_yaml(const algo::TrainingReport& report, const TrainReportContext& context) {
  YAML::Emitter out;
  out.SetDoublePrecision(8);
  out << YAML::Comment(
      "cellsight training report; accuracies are fractions (0.983 = 98.3 %); confusion rows are the true class,\n"
      "columns the predicted class, both in the order of `classes`");
  out << YAML::BeginMap;
  out << YAML::Key << "format_version" << YAML::Value << kReportFormatVersion;
  out << YAML::Key << "date" << YAML::Value << (context.date.empty() ? base::local_time_text() : context.date);
  out << YAML::Key << "model_db" << YAML::Value << context.model_db_path;
  out << YAML::Key << "dataset" << YAML::Value << context.dataset;
  out << YAML::Key << "feature_version" << YAML::Value << context.feature_version;
  out << YAML::Key << "feature_count" << YAML::Value << algo::kFeatureCount;
  out << YAML::Key << "classes" << YAML::Value << YAML::Flow << report.class_names;
  out << YAML::Key << "train_samples" << YAML::Value << report.train_samples;
  out << YAML::Key << "test_samples" << YAML::Value << report.test_samples;
  out << YAML::Key << "synthetic_samples" << YAML::Value << report.synthetic_samples;
  out << YAML::Key << "search_samples" << YAML::Value << report.search_samples;
  out << YAML::Key << "search_classes" << YAML::Value << YAML::Flow << report.search_class_names;  // [] = all
  out << YAML::Key << "folds" << YAML::Value << report.folds;
  out << YAML::Key << "threads" << YAML::Value << report.threads;
  out << YAML::Key << "seconds" << YAML::Value << report.seconds;
  out << YAML::Key << "stopped" << YAML::Value << report.stopped;
  out << YAML::Key << "target_accuracy" << YAML::Value << context.target_accuracy;
  const algo::SvmHyper& h = report.svm_hyper;
  out << YAML::Key << "svm_hyper" << YAML::Value << YAML::BeginMap;
  out << YAML::Key << "kernel" << YAML::Value << std::string(algo::to_string(h.kernel));
  out << YAML::Key << "c" << YAML::Value << h.c;
  out << YAML::Key << "gamma_factor" << YAML::Value << h.gamma_factor;
  out << YAML::Key << "gamma" << YAML::Value;
  emit_number(out, active_feature_count(report.svm) > 0 ? h.gamma(active_feature_count(report.svm))
                                                        : std::numeric_limits<double>::quiet_NaN());
  out << YAML::Key << "degree" << YAML::Value << h.degree;
  out << YAML::Key << "coef0" << YAML::Value << h.coef0;
  out << YAML::EndMap;
  out << YAML::Key << "classifiers" << YAML::Value << YAML::BeginMap;
  for (const algo::ClassifierReport* r : report_classifiers(report)) {
    out << YAML::Key << report_file_stem(*r) << YAML::Value;
    emit_classifier(out, *r, report.class_names);
  }
  out << YAML::EndMap << YAML::EndMap;
  return std::string(out.c_str()) + "\n";
}

std::string annealing_curve_csv(const algo::ClassifierReport& report) {
  std::string s = "iteration,temperature,candidate_accuracy,current_accuracy,best_accuracy,candidate_active,accepted\n";
  for (const algo::AnnealingStep& st : report.curve) {
    s += string_printf("%d,%.9g,%.9g,%.9g,%.9g,%d,%d\n", st.iteration, st.temperature, st.candidate_accuracy,
                       st.current_accuracy, st.best_accuracy, st.candidate_active, st.accepted ? 1 : 0);
  }
  return s;
}

}  // namespace cellsight::app
