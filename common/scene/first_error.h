// Keeps the first error protobuf's text-format parser reports, with its 1-based line, so that a
// file's loader can say "FILE:LINE: message" (scenes, arm configurations). Header-only: needs
// protobuf's headers only.
#pragma once

#include <google/protobuf/io/tokenizer.h>

#include <string>
#include <utility>

namespace somasim::scene {

class FirstError final : public google::protobuf::io::ErrorCollector {
 public:
  // `fallback`: the message when the parser fails without reporting an error.
  explicit FirstError(std::string fallback) : message_(std::move(fallback)) {}
  void AddError(int line, google::protobuf::io::ColumnNumber column,
                const std::string& message) override {
    if (line_ >= 0) return;
    line_ = line + 1;
    message_ = message + " (column " + std::to_string(column + 1) + ")";
  }
  int line() const { return line_; }  // 1-based; -1 when none was reported
  const std::string& message() const { return message_; }

 private:
  int line_ = -1;
  std::string message_;
};

}  // namespace somasim::scene
