// The recording format (common/recording/recording_file.h): what is written reads back; a file
// cut at any byte reads up to its last whole record and says where it ended; a changed byte is
// refused at its record, naming the offset; a newer format version is refused clearly; the
// golden version-1 file stays readable; a sink that fails (a full disk) is reported.
#include "common/recording/recording_file.h"

#include <gtest/gtest.h>

#include <cerrno>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "tests/support/full_disk_sink.h"
#include "tests/support/temp_files.h"

namespace somasim::recording {
namespace {

// `name` in this process's folder (removed when the test passes), no file there yet.
std::string TempPath(const std::string& name) {
  const std::string dir = somasim::testing::ProcessTempDir("somasim-recording");
  std::string path = dir + "/" + name;
  std::filesystem::remove(path);
  return path;
}

std::string ReadBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::ostringstream bytes;
  bytes << in.rdbuf();
  return bytes.str();
}

void WriteBytes(const std::string& path, const std::string& bytes) {
  std::filesystem::remove(path);
  std::ofstream(path, std::ios::binary) << bytes;
}

RecordingHeader Header() {
  RecordingHeader h;
  h.set_software_version("test");
  h.set_scene_text("name: \"t\"\n");
  h.set_scene_hash(TextHash(h.scene_text()));
  h.set_session("s1");
  h.set_trainee("trainee-07");
  h.set_dt(0.01);
  h.set_checkpoint_interval(100);
  return h;
}

Record Command(uint64_t step) {
  Record r;
  r.set_step(step);
  r.set_sim_time(0.01 * static_cast<double>(step));
  ToolCommand* c = r.mutable_tool_command();
  c->set_tool(1);
  c->set_tool_id("probe");
  for (double v : {0.01, -0.02, 0.03 + 1e-3 * static_cast<double>(step)}) c->add_tip(v);
  for (double v : {1.0, 0.0, 0.0, 0.0}) c->add_orientation(v);
  c->set_buttons(4);
  c->set_sequence(step + 1);
  return r;
}

// A recording of the header and `n` tool commands; returns where each record starts.
std::vector<uint64_t> WriteSample(const std::string& path, int n) {
  std::string error;
  Writer w(CreateFileSink(path, &error));
  EXPECT_TRUE(error.empty()) << error;
  EXPECT_TRUE(w.WriteHeader(Header()));
  std::vector<uint64_t> starts;
  for (int i = 0; i < n; ++i) {
    starts.push_back(w.bytes_written());
    EXPECT_TRUE(w.WriteRecord(Command(static_cast<uint64_t>(i))));
  }
  EXPECT_TRUE(w.Sync());
  starts.push_back(w.bytes_written());
  return starts;
}

TEST(RecordingFile, WhatIsWrittenReadsBack) {
  const std::string path = TempPath("roundtrip.somarec");
  const std::vector<uint64_t> starts = WriteSample(path, 20);
  Reader reader(path);
  EXPECT_EQ(reader.format_version(), kFormatVersion);
  EXPECT_EQ(reader.header().trainee(), "trainee-07");
  EXPECT_EQ(reader.header().scene_hash(), TextHash("name: \"t\"\n"));
  Record r;
  for (int i = 0; i < 20; ++i) {
    ASSERT_TRUE(reader.Next(&r)) << i;
    EXPECT_EQ(r.step(), static_cast<uint64_t>(i));
    EXPECT_EQ(r.tool_command().tip(2), 0.03 + 1e-3 * i);  // doubles bit for bit
  }
  EXPECT_FALSE(reader.Next(&r));
  EXPECT_FALSE(reader.truncated());
  EXPECT_EQ(reader.end_offset(), starts.back());
  EXPECT_EQ(reader.records_read(), 20U);
}

TEST(RecordingFile, ARecordingIsNeverOverwritten) {
  const std::string path = TempPath("exists.somarec");
  WriteSample(path, 1);
  std::string error;
  EXPECT_EQ(CreateFileSink(path, &error), nullptr);
  EXPECT_NE(error.find("never overwritten"), std::string::npos) << error;
}

TEST(RecordingFile, ACutAtAnyByteReadsUpToTheLastWholeRecord) {
  const std::string path = TempPath("whole.somarec");
  const std::vector<uint64_t> starts = WriteSample(path, 12);
  const std::string bytes = ReadBytes(path);
  const std::string cut_path = TempPath("cut.somarec");
  for (size_t size = 0; size < bytes.size(); ++size) {
    WriteBytes(cut_path, bytes.substr(0, size));
    if (size < starts.front()) {  // inside the preamble or the header
      EXPECT_THROW(Reader{cut_path}, RecordingError) << size;
      continue;
    }
    Reader reader(cut_path);
    Record r;
    uint64_t read = 0;
    while (reader.Next(&r)) ++read;
    // The whole records before the cut, and where the last of them ends.
    uint64_t whole = 0;
    while (whole + 1 < starts.size() && starts[whole + 1] <= size) ++whole;
    EXPECT_EQ(read, whole) << size;
    EXPECT_EQ(reader.end_offset(), starts[whole]) << size;
    EXPECT_EQ(reader.truncated(), size != starts[whole]) << size;
  }
}

TEST(RecordingFile, AChangedByteIsRefusedAtItsRecordNamingTheOffset) {
  const std::string path = TempPath("whole2.somarec");
  const std::vector<uint64_t> starts = WriteSample(path, 12);
  const std::string bytes = ReadBytes(path);
  const std::string bad_path = TempPath("bad.somarec");
  std::mt19937 rng(7);
  for (int trial = 0; trial < 200; ++trial) {
    std::string bad = bytes;
    const size_t at = std::uniform_int_distribution<size_t>(0, bytes.size() - 1)(rng);
    bad[at] = static_cast<char>(bad[at] ^ (1 + static_cast<int>(rng() % 255)));
    WriteBytes(bad_path, bad);
    if (at < starts.front()) {  // the preamble or the header
      EXPECT_THROW(Reader{bad_path}, RecordingError) << at;
      continue;
    }
    size_t record = 0;
    while (starts[record + 1] <= at) ++record;
    Reader reader(bad_path);
    Record r;
    uint64_t read = 0;
    try {
      while (reader.Next(&r)) ++read;
      // A changed length can only make the record look longer than the file: truncated.
      EXPECT_TRUE(reader.truncated()) << "byte " << at;
      EXPECT_EQ(reader.end_offset(), starts[record]) << at;
    } catch (const RecordingError& e) {
      EXPECT_EQ(e.offset(), starts[record]) << "byte " << at << ": " << e.what();
      EXPECT_NE(std::string(e.what()).find("byte " + std::to_string(starts[record])),
                std::string::npos)
          << e.what();
    }
    EXPECT_EQ(read, record) << "the records before the bad one are read";
  }
}

TEST(RecordingFile, ANewerFormatIsRefusedClearlyAndOtherFilesAreNotRecordings) {
  const std::string path = TempPath("newer.somarec");
  WriteSample(path, 2);
  std::string bytes = ReadBytes(path);
  bytes[8] = static_cast<char>(kFormatVersion + 1);
  WriteBytes(path, bytes);
  try {
    Reader reader(path);
    FAIL() << "a newer format was read";
  } catch (const RecordingError& e) {
    EXPECT_NE(std::string(e.what()).find("format version 2"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("newer"), std::string::npos) << e.what();
  }
  const std::string text = TempPath("text.somarec");
  WriteBytes(text, "somasim-script 1\nkey 0 0 0 0\n");
  try {
    Reader reader(text);
    FAIL() << "a text file was read as a recording";
  } catch (const RecordingError& e) {
    EXPECT_NE(std::string(e.what()).find("not a somasim recording"), std::string::npos);
  }
  EXPECT_THROW(Reader{TempPath("missing.somarec")}, RecordingError);
}

// tests/data/recordings/v1_kidney.somarec: written by somasim-server 0.1.0 (format 1) on
// builtin:kidney424 with --duration 0.05 while a test drove the probe; see its README.
TEST(RecordingFile, TheGoldenVersion1FileStaysReadable) {
  Reader reader(std::string(SOMASIM_TEST_DATA_DIR) + "/recordings/v1_kidney.somarec");
  EXPECT_EQ(reader.format_version(), 1U);
  EXPECT_EQ(reader.header().software_version(), "0.1.0");
  EXPECT_EQ(reader.header().scene_hash(), TextHash(reader.header().scene_text()));
  EXPECT_DOUBLE_EQ(reader.header().dt(), 0.01);
  Record r;
  int commands = 0, checkpoints = 0, ends = 0;
  while (reader.Next(&r)) {
    commands += r.has_tool_command() ? 1 : 0;
    checkpoints += r.has_checkpoint() ? 1 : 0;
    ends += r.has_end() ? 1 : 0;
  }
  EXPECT_FALSE(reader.truncated());
  EXPECT_GT(commands, 0);
  EXPECT_GT(checkpoints, 0);
  EXPECT_EQ(ends, 1);
}

TEST(RecordingFile, AFullDiskIsReportedAndStopsTheWriter) {
  Writer w(std::make_unique<testing::FullDiskSink>(400));
  ASSERT_TRUE(w.WriteHeader(Header()));
  int written = 0;
  while (w.WriteRecord(Command(static_cast<uint64_t>(written)))) ++written;
  EXPECT_GT(written, 0);
  EXPECT_NE(w.error().find("No space left"), std::string::npos) << w.error();
  EXPECT_FALSE(w.WriteRecord(Command(99))) << "a failed writer writes nothing more";
  EXPECT_FALSE(w.Sync());
  // The real thing: /dev/full.
  std::string error;
  std::unique_ptr<Sink> full = CreateFileSink("/dev/full", &error);
  ASSERT_NE(full, nullptr) << error;
  Writer dev(std::move(full));
  EXPECT_FALSE(dev.WriteHeader(Header()));
  EXPECT_NE(dev.error().find("No space left"), std::string::npos) << dev.error();
}

}  // namespace
}  // namespace somasim::recording
