// Logging: one line per event with monotonic time and level; lines below the level are dropped.
#include <unistd.h>

#include <catch2/catch.hpp>
#include <cstdio>
#include <string>

#include "drivers/log.hpp"

using namespace cellsight;

namespace {

// Runs `emit` with stderr redirected into a pipe and returns what it wrote.
template <class F>
std::string capture_stderr(F emit) {
  int fds[2];
  REQUIRE(::pipe(fds) == 0);
  const int saved = ::dup(STDERR_FILENO);
  ::dup2(fds[1], STDERR_FILENO);
  emit();
  ::dup2(saved, STDERR_FILENO);
  ::close(saved);
  ::close(fds[1]);
  std::string out;
  char buf[4096];
  ssize_t n = 0;
  while ((n = ::read(fds[0], buf, sizeof buf)) > 0) out.append(buf, static_cast<std::size_t>(n));
  ::close(fds[0]);
  return out;
}

}  // namespace

TEST_CASE(
    "Given level info, when events of each level are logged, then debug is dropped and each line carries "
    "monotonic seconds, level and component") {
  log::set_level(log::Level::kInfo);
  const std::string out = capture_stderr([] {
    CS_LOG_DEBUG("cam", "hidden %d", 1);
    CS_LOG_INFO("cam", "frame %d", 7);
    CS_LOG_WARN("plc", "late");
    CS_LOG_ERROR("gpio", "chip %s missing", "gpiochip9");
  });
  // Every line: "<seconds>.<3 digits> <LEVEL> <component>: <text>". (std::regex trips a GCC 12 false warning.)
  std::size_t start = 0;
  while (start < out.size()) {
    const std::size_t end = out.find('\n', start);
    REQUIRE(end != std::string::npos);
    const std::string line = out.substr(start, end - start);
    const std::size_t dot = line.find('.');
    REQUIRE(dot != std::string::npos);
    REQUIRE(dot > 0);
    for (std::size_t i = 0; i < dot; ++i) CHECK(std::isdigit(static_cast<unsigned char>(line[i])));
    for (std::size_t i = dot + 1; i < dot + 4; ++i) CHECK(std::isdigit(static_cast<unsigned char>(line[i])));
    CHECK(line[dot + 4] == ' ');
    const std::string rest = line.substr(dot + 5);
    CHECK((rest.rfind("INFO ", 0) == 0 || rest.rfind("WARN ", 0) == 0 || rest.rfind("ERROR ", 0) == 0));
    CHECK(rest.find(": ") != std::string::npos);
    start = end + 1;
  }
  CHECK(out.find("hidden") == std::string::npos);
  CHECK(out.find("INFO cam: frame 7\n") != std::string::npos);
  CHECK(out.find("ERROR gpio: chip gpiochip9 missing\n") != std::string::npos);
  CHECK(std::count(out.begin(), out.end(), '\n') == 3);
}

TEST_CASE("Given a very long message, when logged, then it is cut to one line that still ends with a newline") {
  log::set_level(log::Level::kInfo);
  const std::string long_text(5000, 'x');
  const std::string out = capture_stderr([&] { CS_LOG_INFO("t", "%s", long_text.c_str()); });
  CHECK(out.size() < 1100);
  CHECK(out.back() == '\n');
  CHECK(std::count(out.begin(), out.end(), '\n') == 1);
}

TEST_CASE("Given level names, when parsed, then the five levels are known and others refused") {
  log::Level level{};
  CHECK(log::parse_level("debug", level));
  CHECK(level == log::Level::kDebug);
  CHECK(log::parse_level("off", level));
  CHECK(level == log::Level::kOff);
  CHECK_FALSE(log::parse_level("verbose", level));
}
