// Expected-style result for start-up and tool paths: a value or an Error with a message for a person. In base/ so
// that every layer (base, algo, drivers, formats, runtime, app, cli) returns the same type.
#pragma once

#include <string>
#include <utility>
#include <variant>

namespace cellsight::base {

// A failure that a user reads: say what, where and what to do. Built only off the real-time path.
struct Error {
  std::string message;
};

template <class T>
class [[nodiscard]] Expected {
 public:
  Expected(T value) : v_(std::move(value)) {}      // NOLINT(google-explicit-constructor): value-or-error sugar
  Expected(Error error) : v_(std::move(error)) {}  // NOLINT(google-explicit-constructor)

  [[nodiscard]] bool ok() const { return v_.index() == 0; }
  explicit operator bool() const { return ok(); }
  T& value() & { return std::get<0>(v_); }
  const T& value() const& { return std::get<0>(v_); }
  T&& value() && { return std::get<0>(std::move(v_)); }
  T& operator*() & { return value(); }
  const T& operator*() const& { return value(); }
  T* operator->() { return &value(); }
  const T* operator->() const { return &value(); }
  [[nodiscard]] const Error& error() const { return std::get<1>(v_); }

 private:
  std::variant<T, Error> v_;
};

template <>
class [[nodiscard]] Expected<void> {
 public:
  Expected() = default;
  Expected(Error error) : error_(std::move(error)), ok_(false) {}  // NOLINT(google-explicit-constructor)
  [[nodiscard]] bool ok() const { return ok_; }
  explicit operator bool() const { return ok_; }
  [[nodiscard]] const Error& error() const { return error_; }

 private:
  Error error_;
  bool ok_ = true;
};

using Status = Expected<void>;

inline Error make_error(std::string message) {
  return Error{std::move(message)};
}

}  // namespace cellsight::base

// The result vocabulary of every layer (algo, drivers, formats, runtime, app, cli), written unqualified there: also
// declared in cellsight itself, where each layer's namespace finds it.
namespace cellsight {
using base::Error;
using base::Expected;
using base::make_error;
using base::Status;
}  // namespace cellsight
