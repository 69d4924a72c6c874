#include "common/recording/recording_file.h"

#include <fcntl.h>
#include <unistd.h>
#include <zlib.h>

#include <cerrno>
#include <cstring>

namespace somasim::recording {
namespace {

void PutU32(uint32_t v, char* out) {
  for (int i = 0; i < 4; ++i) out[i] = static_cast<char>((v >> (8 * i)) & 0xFFU);
}

uint32_t GetU32(const char* in) {
  uint32_t v = 0;
  for (int i = 0; i < 4; ++i) v |= static_cast<uint32_t>(static_cast<uint8_t>(in[i])) << (8 * i);
  return v;
}

uint32_t Crc32Of(const std::string& bytes, size_t from) {
  return Crc32({reinterpret_cast<const uint8_t*>(bytes.data()) + from, bytes.size() - from});
}

class FileSink final : public Sink {
 public:
  FileSink(int fd, std::string path) : fd_(fd), path_(std::move(path)) {}
  ~FileSink() override { ::close(fd_); }
  FileSink(const FileSink&) = delete;
  FileSink& operator=(const FileSink&) = delete;
  bool Write(const void* data, size_t size, std::string* error) override {
    const char* p = static_cast<const char*>(data);
    while (size > 0) {
      const ssize_t n = ::write(fd_, p, size);
      if (n < 0 && errno == EINTR) continue;
      if (n <= 0) {
        *error = "cannot write " + path_ + ": " + std::strerror(n < 0 ? errno : EIO);
        return false;
      }
      p += n;
      size -= static_cast<size_t>(n);
    }
    return true;
  }
  bool Sync(std::string* error) override {
    if (::fsync(fd_) != 0 && errno != EINVAL && errno != EROFS) {
      *error = "cannot fsync " + path_ + ": " + std::strerror(errno);
      return false;
    }
    return true;
  }

 private:
  int fd_;
  std::string path_;
};

}  // namespace

uint32_t Crc32(std::span<const uint8_t> bytes) {
  uLong crc = crc32(0L, Z_NULL, 0);
  size_t at = 0;
  while (at < bytes.size()) {
    const auto n = static_cast<uInt>(std::min<size_t>(bytes.size() - at, 1U << 30));
    crc = crc32(crc, bytes.data() + at, n);
    at += n;
  }
  return static_cast<uint32_t>(crc);
}

std::string TextHash(const std::string& text) {
  uint64_t h = 14695981039346656037ULL;
  for (const char c : text) {
    h ^= static_cast<uint8_t>(c);
    h *= 1099511628211ULL;
  }
  char out[17];
  std::snprintf(out, sizeof out, "%016llx", static_cast<unsigned long long>(h));
  return out;
}

std::unique_ptr<Sink> CreateFileSink(const std::string& path, std::string* error) {
  // O_EXCL: a recording is never overwritten; /dev/full and other devices open as they are.
  int flags = O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC;
  if (path.rfind("/dev/", 0) == 0) flags = O_WRONLY | O_CLOEXEC;
  const int fd = ::open(path.c_str(), flags, 0640);
  if (fd < 0) {
    *error = "cannot create the recording " + path + ": " + std::strerror(errno) +
             (errno == EEXIST ? " (a recording is never overwritten: choose a new name)" : "");
    return nullptr;
  }
  return std::make_unique<FileSink>(fd, path);
}

Writer::Writer(std::unique_ptr<Sink> sink) : sink_(std::move(sink)) {}

bool Writer::Put(const std::string& payload, bool with_preamble) {
  if (!error_.empty()) return false;
  buffer_.clear();
  if (with_preamble) {
    buffer_.append(kMagic, sizeof kMagic);
    char v[4];
    PutU32(kFormatVersion, v);
    buffer_.append(v, 4);
  }
  char head[8];
  PutU32(static_cast<uint32_t>(payload.size()), head);
  PutU32(Crc32({reinterpret_cast<const uint8_t*>(payload.data()), payload.size()}), head + 4);
  buffer_.append(head, 8);
  buffer_.append(payload);
  if (!sink_->Write(buffer_.data(), buffer_.size(), &error_)) return false;
  bytes_ += buffer_.size();
  return true;
}

bool Writer::WriteHeader(const RecordingHeader& header) {
  return Put(header.SerializeAsString(), true);
}

bool Writer::WriteRecord(const Record& record) {
  if (!Put(record.SerializeAsString(), false)) return false;
  ++records_;
  return true;
}

bool Writer::Sync() {
  if (!error_.empty()) return false;
  return sink_->Sync(&error_);
}

Reader::Reader(const std::string& path) : path_(path) {
  file_ = std::fopen(path.c_str(), "rb");
  if (file_ == nullptr) {
    throw RecordingError("cannot open the recording " + path + ": " + std::strerror(errno), 0);
  }
  if (!ReadExactly(12) || std::memcmp(buffer_.data(), kMagic, sizeof kMagic) != 0) {
    std::fclose(file_);
    file_ = nullptr;
    throw RecordingError(path + " is not a somasim recording (no SOMAREC magic at its start)", 0);
  }
  version_ = GetU32(buffer_.data() + 8);
  if (version_ > kFormatVersion || version_ == 0) {
    std::fclose(file_);
    file_ = nullptr;
    throw RecordingError(path + " has recording format version " + std::to_string(version_) +
                             "; this somasim reads versions 1 to " +
                             std::to_string(kFormatVersion) + " (a newer somasim wrote it)",
                         8);
  }
  const bool complete = ReadExactly(8);
  const uint32_t size = complete ? GetU32(buffer_.data()) : 0;
  const uint32_t crc = complete ? GetU32(buffer_.data() + 4) : 0;
  if (!complete || size > kMaxRecordSize || !ReadExactly(size)) {
    std::fclose(file_);
    file_ = nullptr;
    throw RecordingError(path + ": the header is truncated", 12);
  }
  if (Crc32Of(buffer_, 0) != crc || !header_.ParseFromString(buffer_)) {
    std::fclose(file_);
    file_ = nullptr;
    throw RecordingError(path + ": the header fails its checksum (corrupt) at byte 12", 12);
  }
  offset_ = kPreambleSize + size;
}

Reader::~Reader() {
  if (file_ != nullptr) std::fclose(file_);
}

bool Reader::ReadExactly(size_t n) {
  buffer_.resize(n);
  return n == 0 || std::fread(buffer_.data(), 1, n, file_) == n;
}

bool Reader::Next(Record* record) {
  if (truncated_) return false;
  const uint64_t start = offset_;
  if (!ReadExactly(8)) {
    // Nothing more (a clean end) or a part of a record's length and checksum (truncated).
    truncated_ = std::ftell(file_) > static_cast<long>(start);
    return false;
  }
  const uint32_t size = GetU32(buffer_.data());
  const uint32_t crc = GetU32(buffer_.data() + 4);
  if (size > kMaxRecordSize) {
    throw RecordingError(path_ + ": the record at byte " + std::to_string(start) + " claims " +
                             std::to_string(size) + " bytes (corrupt)",
                         start);
  }
  if (!ReadExactly(size)) {
    truncated_ = true;
    return false;
  }
  if (Crc32Of(buffer_, 0) != crc) {
    throw RecordingError(path_ + ": the record at byte " + std::to_string(start) +
                             " fails its checksum (corrupt); the replay stops there",
                         start);
  }
  if (!record->ParseFromString(buffer_)) {
    throw RecordingError(
        path_ + ": the record at byte " + std::to_string(start) + " does not parse (corrupt)",
        start);
  }
  offset_ = start + 8 + size;
  ++records_;
  return true;
}

}  // namespace somasim::recording
