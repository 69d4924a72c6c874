// somasim-mesh render, in-process: the PNG it writes, and the exit code and message of every
// way it can fail. Small pictures keep it quick under the sanitizers.
#include "common/tools/render_command.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <cstdint>
#include <filesystem>
#include <limits>
#include <sstream>
#include <string>

#include "common/mesh_io/mesh_io.h"
#include "common/tools/mesh_commands.h"
#include "tests/support/mesh_fixtures.h"

namespace somasim::tools {
namespace {

struct RenderRun {
  int status = -1;
  std::string out, err;
};

RenderRun Render(const RenderCommandOptions& options) {
  std::ostringstream out, err;
  RenderRun run;
  run.status = RunRender(options, out, err);
  run.out = out.str();
  run.err = err.str();
  return run;
}

uint32_t ReadU32(const std::string& s, size_t at) {
  return (uint32_t{static_cast<uint8_t>(s[at])} << 24) |
         (uint32_t{static_cast<uint8_t>(s[at + 1])} << 16) |
         (uint32_t{static_cast<uint8_t>(s[at + 2])} << 8) |
         uint32_t{static_cast<uint8_t>(s[at + 3])};
}

// Checks the signature and IHDR of a PNG file and returns its {width, height}.
std::pair<uint32_t, uint32_t> PngSize(const std::string& bytes) {
  if (bytes.size() < 33 || bytes.compare(0, 8, std::string("\x89PNG\r\n\x1a\n", 8)) != 0 ||
      bytes.compare(12, 4, "IHDR") != 0) {
    ADD_FAILURE() << "not a PNG (" << bytes.size() << " bytes)";
    return {0, 0};
  }
  EXPECT_EQ(bytes.compare(bytes.size() - 8, 4, "IEND"), 0) << "no IEND at the end";
  return {ReadU32(bytes, 16), ReadU32(bytes, 20)};
}

// A small volume mesh written to a fresh temp dir; returns its path.
std::string BoxFile(const std::string& dir) {
  std::string path = dir + "/box.vtu";
  mesh_io::WriteMeshFile(path, testing::BoxTets(3, 2, 1, 0.06, 0.04, 0.02), {});
  return path;
}

TEST(RenderCommand, WritesAPngOfTheRequestedSizeFromAVolumeMesh) {
  const std::string dir = testing::MakeTempDir("somasim-render");
  RenderCommandOptions o;
  o.input = BoxFile(dir);
  o.output = dir + "/box.png";
  o.width = 64;
  o.height = 40;
  const RenderRun run = Render(o);
  ASSERT_EQ(run.status, kExitOk) << run.err;
  EXPECT_TRUE(run.err.empty()) << run.err;
  EXPECT_NE(run.out.find("wrote " + o.output + ": 64x40 PNG"), std::string::npos) << run.out;
  EXPECT_NE(run.out.find("boundary of 36 tetrahedra"), std::string::npos) << run.out;
  EXPECT_EQ(PngSize(testing::Slurp(o.output)), (std::pair<uint32_t, uint32_t>{64, 40}));
}

TEST(RenderCommand, RendersASurfaceMeshInItsOwnUnit) {
  const std::string dir = testing::MakeTempDir("somasim-render");
  RenderCommandOptions o;
  o.input = testing::SharedMesh("liver.obj");
  o.read.unit = mesh_io::Unit::kCentimetre;
  o.output = dir + "/liver.PNG";  // the extension check ignores case
  o.width = 48;
  o.height = 36;
  o.view = Eigen::Vector3d(0, 0, -1);
  const RenderRun run = Render(o);
  ASSERT_EQ(run.status, kExitOk) << run.err;
  EXPECT_EQ(run.out.find("tetrahedra"), std::string::npos) << run.out;
  EXPECT_EQ(PngSize(testing::Slurp(o.output)), (std::pair<uint32_t, uint32_t>{48, 36}));
}

TEST(RenderCommand, SameInputGivesTheSameFileAndEdgesChangeIt) {
  const std::string dir = testing::MakeTempDir("somasim-render");
  RenderCommandOptions o;
  o.input = BoxFile(dir);
  o.width = 40;
  o.height = 30;
  o.output = dir + "/a.png";
  ASSERT_EQ(Render(o).status, kExitOk);
  o.output = dir + "/b.png";
  ASSERT_EQ(Render(o).status, kExitOk);
  o.output = dir + "/plain.png";
  o.edges = false;
  ASSERT_EQ(Render(o).status, kExitOk);
  EXPECT_EQ(testing::Slurp(dir + "/a.png"), testing::Slurp(dir + "/b.png"));
  EXPECT_NE(testing::Slurp(dir + "/a.png"), testing::Slurp(dir + "/plain.png"));
}

TEST(RenderCommand, OverwritesAnExistingOutput) {
  const std::string dir = testing::MakeTempDir("somasim-render");
  RenderCommandOptions o;
  o.input = BoxFile(dir);
  o.output = dir + "/out.png";
  o.width = 16;
  o.height = 16;
  testing::WriteBytes(o.output, std::string(100000, 'x'));
  ASSERT_EQ(Render(o).status, kExitOk);
  EXPECT_EQ(PngSize(testing::Slurp(o.output)), (std::pair<uint32_t, uint32_t>{16, 16}));
}

TEST(RenderCommand, MalformedInputExitsThreeNamingTheFile) {
  const std::string dir = testing::MakeTempDir("somasim-render");
  RenderCommandOptions o;
  o.input = dir + "/broken.obj";
  testing::WriteBytes(o.input, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n");
  o.output = dir + "/out.png";
  const RenderRun run = Render(o);
  EXPECT_EQ(run.status, kExitBadInput) << run.err;
  EXPECT_NE(run.err.find("broken.obj"), std::string::npos) << run.err;
  EXPECT_FALSE(std::filesystem::exists(o.output));
  // A real broken file from the shared meshes too.
  o.input = testing::SharedMesh("6_tetra_bad.msh");
  const RenderRun shared = Render(o);
  EXPECT_EQ(shared.status, kExitBadInput) << shared.err;
  EXPECT_NE(shared.err.find("6_tetra_bad.msh"), std::string::npos) << shared.err;
}

TEST(RenderCommand, MissingInputExitsFour) {
  RenderCommandOptions o;
  o.input = "/nonexistent/mesh.vtu";
  o.output = testing::MakeTempDir("somasim-render") + "/out.png";
  const RenderRun run = Render(o);
  EXPECT_EQ(run.status, kExitIo) << run.err;
  EXPECT_NE(run.err.find("/nonexistent/mesh.vtu"), std::string::npos) << run.err;
}

TEST(RenderCommand, UnwritableOutputExitsFourNamingIt) {
  const std::string dir = testing::MakeTempDir("somasim-render");
  RenderCommandOptions o;
  o.input = BoxFile(dir);
  o.width = 16;
  o.height = 16;
  o.output = dir + "/no/such/dir/out.png";
  const RenderRun missing_dir = Render(o);
  EXPECT_EQ(missing_dir.status, kExitIo) << missing_dir.err;
  EXPECT_NE(missing_dir.err.find(o.output), std::string::npos) << missing_dir.err;
  EXPECT_NE(missing_dir.err.find("cannot create"), std::string::npos) << missing_dir.err;
  o.output = dir + "/isdir.png";  // a directory is not a writable file, whatever its name
  std::filesystem::create_directory(o.output);
  EXPECT_EQ(Render(o).status, kExitIo);
  if (access("/dev/full", W_OK) == 0) {
    // A device that accepts the open but fails every write: the write error is caught.
    const std::string full = dir + "/full.png";
    std::filesystem::create_symlink("/dev/full", full);
    o.output = full;
    const RenderRun run = Render(o);
    EXPECT_EQ(run.status, kExitIo) << run.err;
    EXPECT_NE(run.err.find("write failed"), std::string::npos) << run.err;
  }
}

TEST(RenderCommand, BadSizeViewOrOutputNameExitsTwo) {
  const std::string dir = testing::MakeTempDir("somasim-render");
  RenderCommandOptions base;
  base.input = BoxFile(dir);
  base.output = dir + "/out.png";
  const auto status_with = [&](auto change) {
    RenderCommandOptions o = base;
    change(o);
    const RenderRun run = Render(o);
    EXPECT_FALSE(run.err.empty());
    return run.status;
  };
  EXPECT_EQ(status_with([](RenderCommandOptions& o) { o.width = 0; }), kExitUsage);
  EXPECT_EQ(status_with([](RenderCommandOptions& o) { o.height = 8193; }), kExitUsage);
  EXPECT_EQ(status_with([](RenderCommandOptions& o) { o.view = Eigen::Vector3d::Zero(); }),
            kExitUsage);
  EXPECT_EQ(status_with([](RenderCommandOptions& o) {
              o.view = Eigen::Vector3d(std::numeric_limits<double>::quiet_NaN(), 0, 1);
            }),
            kExitUsage);
  EXPECT_EQ(status_with([&](RenderCommandOptions& o) { o.output = dir + "/out.msh"; }), kExitUsage);
  EXPECT_FALSE(std::filesystem::exists(dir + "/out.msh"));
  EXPECT_FALSE(std::filesystem::exists(base.output));
}

TEST(RenderCommand, ParsesSizesAndVectors) {
  EXPECT_EQ(ParseImageSize("800x600"), (std::pair{800, 600}));
  EXPECT_EQ(ParseImageSize("1X2"), (std::pair{1, 2}));
  for (const char* bad :
       {"", "800", "x600", "800x", "0x600", "-8x6", "8x6x2", "1e3x5", "999999x1", " 8x6", "8 x6"}) {
    EXPECT_FALSE(ParseImageSize(bad).has_value()) << bad;
  }
  EXPECT_EQ(ParseVector3("1,-2.5,+3e-1"), Eigen::Vector3d(1, -2.5, 0.3));
  for (const char* bad :
       {"", "1,2", "1,2,3,4", "1,,3", "a,b,c", "1,2,nan", "1,2,inf", "1,2,3 ", "1,2,+-3"}) {
    EXPECT_FALSE(ParseVector3(bad).has_value()) << bad;
  }
}

}  // namespace
}  // namespace somasim::tools
