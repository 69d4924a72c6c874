// A recording sink (common/recording/recording_file.h) with room for a fixed number of bytes
// that then fails as a full disk does (ENOSPC): the injected write failure of the recording
// tests.
#pragma once

#include <cerrno>
#include <cstring>
#include <string>

#include "common/recording/recording_file.h"

namespace somasim::testing {

class FullDiskSink final : public recording::Sink {
 public:
  explicit FullDiskSink(size_t room) : room_(room) {}
  bool Write(const void* /*data*/, size_t size, std::string* error) override {
    if (size > room_) {
      *error = std::string("cannot write: ") + std::strerror(ENOSPC);
      return false;
    }
    room_ -= size;
    return true;
  }
  bool Sync(std::string* /*error*/) override { return true; }

 private:
  size_t room_;
};

}  // namespace somasim::testing
