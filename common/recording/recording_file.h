// Session recordings on disk (issue 11; the format: idl/recording.proto, docs/recording.md):
// a header, then length-delimited protobuf records, each with a CRC-32. Writing goes to a Sink
// (a file, or a test's sink that fails on purpose); reading checks every checksum and says
// where a file ends early. No threads here: the server's recorder (server/app/recorder.h) runs
// the writer on its own thread.
#pragma once

#include <cstdint>
#include <cstdio>
#include <memory>
#include <span>
#include <stdexcept>
#include <string>

#include "idl/recording.pb.h"

namespace somasim::recording {

inline constexpr char kMagic[8] = {'S', 'O', 'M', 'A', 'R', 'E', 'C', '\n'};
inline constexpr uint32_t kFormatVersion = 1;
// Bytes before the header: magic, version, header length, header CRC-32.
inline constexpr size_t kPreambleSize = 20;
// A record or header longer than this [bytes] is refused (a corrupt length, not a recording).
inline constexpr uint32_t kMaxRecordSize = 256U << 20;

// CRC-32 (zlib's, ISO-HDLC) of `bytes`.
uint32_t Crc32(std::span<const uint8_t> bytes);
// FNV-1a 64 of `text` as 16 lower-case hex digits (the scene's hash in the header).
std::string TextHash(const std::string& text);

// Where the writer's bytes go.
class Sink {
 public:
  virtual ~Sink() = default;
  // Appends all of `size` bytes; false with `error` set when it cannot.
  virtual bool Write(const void* data, size_t size, std::string* error) = 0;
  // Makes what was written durable (fsync); false with `error` set when it cannot.
  virtual bool Sync(std::string* error) = 0;
};

// A new file at `path` (an existing file is never overwritten: a recording is evidence). Null
// with `error` set when it cannot be created.
std::unique_ptr<Sink> CreateFileSink(const std::string& path, std::string* error);

class Writer {
 public:
  explicit Writer(std::unique_ptr<Sink> sink);
  // The preamble and the header. False on a write error (then error() says which).
  bool WriteHeader(const RecordingHeader& header);
  bool WriteRecord(const Record& record);
  bool Sync();
  const std::string& error() const { return error_; }
  uint64_t bytes_written() const { return bytes_; }
  uint64_t records_written() const { return records_; }

 private:
  bool Put(const std::string& payload, bool with_preamble);
  std::unique_ptr<Sink> sink_;
  std::string buffer_;  // one record's bytes, reused
  std::string error_;
  uint64_t bytes_ = 0;
  uint64_t records_ = 0;
};

// What is wrong with a recording, and where (the byte offset of the header or the record).
class RecordingError : public std::runtime_error {
 public:
  RecordingError(const std::string& message, uint64_t offset)
      : std::runtime_error(message), offset_(offset) {}
  uint64_t offset() const { return offset_; }

 private:
  uint64_t offset_;
};

class Reader {
 public:
  // Opens `path` and reads its header. Throws RecordingError for a file that cannot be read, is
  // not a recording, comes from a newer format version, or whose header is truncated or fails
  // its checksum.
  explicit Reader(const std::string& path);
  ~Reader();
  Reader(const Reader&) = delete;
  Reader& operator=(const Reader&) = delete;

  const RecordingHeader& header() const { return header_; }
  uint32_t format_version() const { return version_; }
  // The next record: true; false at the end of the file. At a clean end truncated() is false;
  // when the file ends inside a record (a crash while writing, a cut copy) truncated() is true
  // and end_offset() is where the incomplete record starts. Throws RecordingError for a record
  // whose checksum does not match or that does not parse (offset: the record's).
  bool Next(Record* record);
  bool truncated() const { return truncated_; }
  uint64_t end_offset() const { return offset_; }  // bytes of whole, good records and header
  uint64_t records_read() const { return records_; }

 private:
  // Reads exactly n bytes into buffer_; false when the file ends first.
  bool ReadExactly(size_t n);
  std::FILE* file_ = nullptr;
  std::string path_;
  RecordingHeader header_;
  uint32_t version_ = 0;
  std::string buffer_;
  uint64_t offset_ = 0;
  uint64_t records_ = 0;
  bool truncated_ = false;
};

}  // namespace somasim::recording
