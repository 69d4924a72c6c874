#include "haptic_node/mock_script.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

#include "tests/support/allocation_counter.h"

namespace somasim::haptic {
namespace {

constexpr double kTol = 1e-12;

std::string Script(const std::string& body) { return "somasim-script 1\n" + body; }

// The error Parse gives for `text` (named "t.txt"); one at line -1 when it parses.
ScriptError ErrorOf(const std::string& text) {
  try {
    MockScript::Parse(text, "t.txt");
  } catch (const ScriptError& e) {
    return e;
  }
  return ScriptError("(none)", -1, "parsed");
}

TEST(MockScript, ParsesKeysToolsAndDefaults) {
  const MockScript s = MockScript::Parse(
      "# a comment line\n"
      "\n"
      "somasim-script 1   # the header\n"
      "tool probe\n"
      "key 0 0.01 0.02 0.03\n"
      "  key 0.5\t0.02 0.02 0.03 jaw 0.25 buttons 4\n"
      "tool grasper_2-b\n"
      "key 1.5 0 0 0.1 quat 0 0 0 2\n"
      "key 2 0 0 0.2\n"
      "tool probe\n"
      "key 3 0 0 0.3 buttons 0 jaw 1\n",
      "ok.txt");
  ASSERT_EQ(s.tools().size(), 2U);
  EXPECT_EQ(s.tools()[0], "probe");
  EXPECT_EQ(s.tools()[1], "grasper_2-b");
  ASSERT_EQ(s.keys().size(), 5U);
  const std::vector<ScriptKey>& k = s.keys();
  EXPECT_EQ(k[0].line, 5);
  EXPECT_EQ(k[0].tool, 0);
  EXPECT_TRUE(k[0].position.isApprox(Eigen::Vector3d(0.01, 0.02, 0.03)));
  EXPECT_TRUE(k[0].orientation.coeffs().isApprox(Eigen::Quaterniond::Identity().coeffs()));
  EXPECT_EQ(k[0].jaw, 0.0);
  EXPECT_EQ(k[0].buttons, 0U);
  EXPECT_EQ(k[1].jaw, 0.25);
  EXPECT_EQ(k[1].buttons, 4U);
  EXPECT_EQ(k[2].tool, 1);
  EXPECT_EQ(k[2].line, 8);
  EXPECT_EQ(k[2].jaw, 0.25);    // kept from the previous key
  EXPECT_EQ(k[2].buttons, 4U);  // kept
  // Normalised when read: (0 0 0 2) → (0 0 0 1), a half turn about z.
  EXPECT_NEAR(k[2].orientation.z(), 1.0, kTol);
  EXPECT_NEAR(k[2].orientation.w(), 0.0, kTol);
  EXPECT_NEAR(k[3].orientation.z(), 1.0, kTol);  // kept
  EXPECT_EQ(k[4].tool, 0);                       // "probe" again: the same index
  EXPECT_EQ(k[4].jaw, 1.0);
  EXPECT_EQ(k[4].buttons, 0U);
  EXPECT_EQ(s.duration(), 3.0);
}

TEST(MockScript, AcceptsCrLfLineEndingsAndNoFinalNewline) {
  const MockScript s =
      MockScript::Parse("somasim-script 1\r\ntool probe\r\nkey 0 0 0 0\r\nkey 1 0 0 1", "crlf.txt");
  ASSERT_EQ(s.keys().size(), 2U);
  EXPECT_EQ(s.keys()[1].line, 4);
  EXPECT_EQ(s.duration(), 1.0);
}

struct BadScript {
  std::string text;
  int line;
  std::string message;  // the whole message after "t.txt:LINE: "
};

TEST(MockScript, EveryFaultIsNamedWithItsLine) {
  const std::string t = "tool probe\n";  // line 2 after the header
  const std::vector<BadScript> cases = {
      // The header.
      {"", 1, "empty script: expected the header 'somasim-script 1'"},
      {"# only a comment\n\n", 2, "empty script: expected the header 'somasim-script 1'"},
      {"tool probe\nkey 0 0 0 0\n", 1, "expected the header 'somasim-script 1', got 'tool'"},
      {"somasim-script\n", 1, "somasim-script: missing version (expected 1)"},
      {"somasim-script 2\n", 1, "somasim-script: unsupported version '2' (expected 1)"},
      {"somasim-script 1 x\n", 1, "somasim-script: extra value 'x'"},
      {Script("somasim-script 1\n"), 2, "somasim-script: the header is repeated"},
      // Keywords and tools.
      {Script(t + "move 0 0 0 0\n"), 3, "unknown keyword 'move' (expected tool or key)"},
      {Script("key 0 0 0 0\n"), 2, "key: before any 'tool' line"},
      {Script("tool\n"), 2, "tool: missing ID"},
      {Script("tool probe grasper\n"), 2, "tool: extra value 'grasper'"},
      {Script("tool pro.be\nkey 0 0 0 0\n"), 2,
       "tool: ID 'pro.be' is not letters, digits, '_' or '-'"},
      {Script(t + "tool grasper\nkey 0 0 0 0\n"), 2, "tool: 'probe' is not followed by a key"},
      {Script(t + "key 0 0 0 0\ntool grasper\n"), 4, "tool: 'grasper' is not followed by a key"},
      {Script(t), 2, "tool: 'probe' is not followed by a key"},
      {Script("# no key\n"), 2, "no key in the script"},
      // Missing and extra values.
      {Script(t + "key\n"), 3, "key: missing time T"},
      {Script(t + "key 0 0.1 0.2\n"), 3, "key: missing position Z"},
      {Script(t + "key 0 0 0 0 0.5\n"), 3,
       "key: extra value '0.5' (after T X Y Z come only jaw J, quat W X Y Z, buttons B)"},
      {Script(t + "key 0 0 0 0 jaw\n"), 3, "key: missing jaw J"},
      {Script(t + "key 0 0 0 0 quat 1 0 0\n"), 3, "key: missing quat Z"},
      {Script(t + "key 0 0 0 0 buttons\n"), 3, "key: missing buttons B"},
      {Script(t + "key 0 0 0 0 jaw 0 jaw 1\n"), 3, "key: jaw given twice"},
      // Numbers.
      {Script(t + "key 0 0.1x 0 0\n"), 3, "key: position X '0.1x' is not a number"},
      {Script(t + "key 0 0 , 0\n"), 3, "key: position Y ',' is not a number"},
      {Script(t + "key 0 0 0 +1\n"), 3, "key: position Z '+1' is not a number"},
      {Script(t + "key 0 nan 0 0\n"), 3, "key: position X 'nan' is not a finite number"},
      {Script(t + "key inf 0 0 0\n"), 3, "key: time T 'inf' is not a finite number"},
      {Script(t + "key 0 0 0 -infinity\n"), 3,
       "key: position Z '-infinity' is not a finite number"},
      {Script(t + "key 0 0 0 1e999\n"), 3, "key: position Z '1e999' is out of range"},
      {Script(t + "key 0 0 0 0 jaw NaN\n"), 3, "key: jaw J 'NaN' is not a finite number"},
      {Script(t + "key 0 0 0 0 quat 1 0 nan 0\n"), 3, "key: quat Y 'nan' is not a finite number"},
      // Times, ranges.
      {Script(t + "key -0.5 0 0 0\n"), 3,
       "key: time -0.5 is negative (the first key is at T >= 0)"},
      {Script(t + "key 1 0 0 0\n# gap\nkey 1 0 0 0\n"), 5,
       "key: time 1 does not increase (the key on line 3 is at 1.000000 s)"},
      {Script(t + "key 1 0 0 0\nkey 0.5 0 0 0\n"), 4,
       "key: time 0.5 does not increase (the key on line 3 is at 1.000000 s)"},
      {Script(t + "key 0 0 0 0\n\n\n\nkey 0.5 0 0 0 jaw 1.5\n"), 7,
       "key: jaw 1.5 is outside [0, 1]"},
      {Script(t + "key 0 0 0 0 jaw -0.01\n"), 3, "key: jaw -0.01 is outside [0, 1]"},
      {Script(t + "key 0 0 0 0 quat 0 0 0 0\n"), 3,
       "key: quat 0 0 0 0 has no direction (length 0.000000)"},
      {Script(t + "key 0 0 0 0 buttons -1\n"), 3,
       "key: buttons B '-1' is not an unsigned 32-bit integer"},
      {Script(t + "key 0 0 0 0 buttons 4294967296\n"), 3,
       "key: buttons B '4294967296' is not an unsigned 32-bit integer"},
      {Script(t + "key 0 0 0 0 buttons 1.5\n"), 3,
       "key: buttons B '1.5' is not an unsigned 32-bit integer"},
      {Script(t + "key 0 0 0 0 buttons 0x4\n"), 3,
       "key: buttons B '0x4' is not an unsigned 32-bit integer"},
      {Script(t + "key 0 6 8 0.5\n"), 3,
       "key: position 6 8 0.5 is 10.012492 m from the origin (at most 10 m)"},
  };
  for (const BadScript& c : cases) {
    const ScriptError e = ErrorOf(c.text);
    EXPECT_EQ(e.file(), "t.txt") << c.text;
    EXPECT_EQ(e.line(), c.line) << c.text;
    EXPECT_EQ(std::string(e.what()), "t.txt:" + std::to_string(c.line) + ": " + c.message)
        << c.text;
  }
}

TEST(MockScript, TheDocumentedErrorMessageIsExact) {
  const std::string text =
      "somasim-script 1\n# palpation\ntool probe\nkey 0 0 0 0.1\nkey 1 0 0 0.05\n\nkey 1.5 0 0 "
      "0.05 jaw 1.5\n";
  try {
    MockScript::Parse(text, "palpate.txt");
    FAIL() << "parsed";
  } catch (const ScriptError& error) {
    EXPECT_STREQ(error.what(), "palpate.txt:7: key: jaw 1.5 is outside [0, 1]");
  }
}

TEST(MockScript, EveryIncompleteKeyLineIsRejected) {
  // Cutting the key line after any word that leaves a value group incomplete is an error on
  // its line; cutting it between groups gives a shorter valid key.
  const std::vector<std::string> words = {"key",  "0.5", "0.01", "0.02", "0.03", "jaw",     "0.5",
                                          "quat", "1",   "0",    "0",    "0",    "buttons", "4"};
  const std::vector<size_t> complete = {5, 7, 12, 14};
  for (size_t count = 1; count <= words.size(); ++count) {
    std::string line;
    for (size_t i = 0; i < count; ++i) line += (i > 0 ? " " : "") + words[i];
    const std::string text = Script("tool probe\n" + line + "\n");
    const bool valid = std::find(complete.begin(), complete.end(), count) != complete.end();
    if (valid) {
      EXPECT_NO_THROW(MockScript::Parse(text, "t.txt")) << line;
    } else {
      EXPECT_EQ(ErrorOf(text).line(), 3) << line;
    }
  }
}

TEST(MockScript, LoadNamesTheFileItCannotRead) {
  try {
    MockScript::Load("/nonexistent/dir/script.txt");
    FAIL() << "loaded";
  } catch (const ScriptError& e) {
    EXPECT_EQ(e.line(), 0);
    EXPECT_EQ(e.file(), "/nonexistent/dir/script.txt");
    EXPECT_NE(std::string(e.what()).find("/nonexistent/dir/script.txt:0: cannot open"),
              std::string::npos)
        << e.what();
  }
}

MockScript TwoToolScript() {
  return MockScript::Parse(Script("tool grasper\n"
                                  "key 1 0.0 0.0 0.10 jaw 0 buttons 1\n"
                                  "key 3 0.02 -0.04 0.06 jaw 1 quat 0 1 0 0 buttons 4\n"
                                  "tool scalpel\n"
                                  "key 5 0.1 0.1 0.1 jaw 0 quat 1 0 0 0 buttons 0\n"
                                  "key 6 0.1 0.1 0.0\n"),
                           "two.txt");
}

TEST(MockScript, SamplesAtKeysAreTheKeys) {
  const MockScript s = TwoToolScript();
  for (const ScriptKey& k : s.keys()) {
    const ScriptSample a = s.At(k.time);
    EXPECT_EQ(a.tool, k.tool);
    EXPECT_EQ(a.position, k.position);
    EXPECT_TRUE(a.orientation.coeffs().isApprox(k.orientation.coeffs()));
    EXPECT_EQ(a.jaw, k.jaw);
    EXPECT_EQ(a.buttons, k.buttons);
  }
}

TEST(MockScript, PositionAndJawAreLinearOrientationSlerpedButtonsHeld) {
  const MockScript s = TwoToolScript();
  const ScriptKey& a = s.keys()[0];
  const ScriptKey& b = s.keys()[1];
  for (const double u : {0.1, 0.25, 0.5, 0.9}) {
    const ScriptSample m = s.At(1.0 + 2.0 * u);
    EXPECT_EQ(m.tool, 0);
    EXPECT_NEAR((m.position - (a.position + u * (b.position - a.position))).norm(), 0.0, kTol);
    EXPECT_NEAR(m.jaw, u, kTol);
    EXPECT_EQ(m.buttons, 1U);  // the earlier key's until the next key
    // Identity → a half turn about x: a rotation by u·π about x.
    const Eigen::Quaterniond expected(
        Eigen::AngleAxisd(u * std::numbers::pi, Eigen::Vector3d::UnitX()));
    EXPECT_NEAR(m.orientation.angularDistance(expected), 0.0, 1e-9) << u;
    EXPECT_NEAR(m.orientation.norm(), 1.0, kTol);
  }
}

TEST(MockScript, BeforeTheFirstKeyAndAfterTheLastTheEndKeysHold) {
  const MockScript s = TwoToolScript();
  for (const double t : {-5.0, 0.0, 0.999, std::nan("")}) {
    const ScriptSample m = s.At(t);
    EXPECT_EQ(m.tool, 0) << t;
    EXPECT_EQ(m.position, s.keys().front().position) << t;
    EXPECT_EQ(m.buttons, 1U) << t;
  }
  for (const double t : {6.0, 6.001, 1e9, std::numeric_limits<double>::infinity()}) {
    const ScriptSample m = s.At(t);
    EXPECT_EQ(m.tool, 1) << t;
    EXPECT_EQ(m.position, s.keys().back().position) << t;
  }
}

TEST(MockScript, AcrossAToolSwitchTheOldToolHoldsThenTheNewOneJumps) {
  const MockScript s = TwoToolScript();
  for (const double t : {3.0, 3.5, 4.999}) {
    const ScriptSample m = s.At(t);
    EXPECT_EQ(m.tool, 0) << t;
    EXPECT_EQ(m.position, s.keys()[1].position) << t;
    EXPECT_EQ(m.jaw, 1.0) << t;
    EXPECT_EQ(m.buttons, 4U) << t;
  }
  const ScriptSample first = s.At(5.0);
  EXPECT_EQ(first.tool, 1);
  EXPECT_EQ(first.position, s.keys()[2].position);
  EXPECT_EQ(first.jaw, 0.0);
  const ScriptSample mid = s.At(5.5);
  EXPECT_EQ(mid.tool, 1);
  EXPECT_NEAR((mid.position - Eigen::Vector3d(0.1, 0.1, 0.05)).norm(), 0.0, kTol);
}

TEST(MockScript, AtAllocatesNothing) {
  const MockScript s = TwoToolScript();
  double sum = 0.0;
  int64_t allocations = 0;
  {
    const testing::AllocationCounter counter;
    for (int i = 0; i < 8000; ++i) {
      const ScriptSample m = s.At(1e-3 * i);
      sum += m.position.z() + m.jaw + m.orientation.w();
    }
    allocations = counter.count();
  }
  EXPECT_EQ(allocations, 0);
  EXPECT_TRUE(std::isfinite(sum));
}

// The shipped scripts drive the default session on builtin:liver (liver4055, bounding box
// (-0.1099, -0.0607, -0.0529) .. (0.1230, 0.0749, 0.0709) m). Their documented durations and
// tools (docs/mock_scripts.md), and poses that stay over the organ: within its x-y extent and
// between 2 cm below its top and 5 cm above it.
struct Shipped {
  const char* file;
  double duration;
  std::vector<std::string> tools;
};

MockScript LoadShipped(const char* file) {
  return MockScript::Load(std::string(SOMASIM_SCRIPTS_DIR) + "/" + file);
}

TEST(MockScript, ShippedScriptsParseWithTheirDocumentedDurationsAndTools) {
  const std::vector<Shipped> shipped = {
      {"palpate.txt", 6.0, {"probe"}},
      {"grasp_pull.txt", 7.0, {"grasper"}},
      {"incision.txt", 5.0, {"scalpel"}},
      {"demo.txt", 20.0, {"probe", "grasper", "scalpel"}},
  };
  for (const Shipped& sh : shipped) {
    const MockScript s = LoadShipped(sh.file);
    EXPECT_EQ(s.duration(), sh.duration) << sh.file;
    EXPECT_EQ(s.tools(), sh.tools) << sh.file;
    EXPECT_EQ(s.keys().front().time, 0.0) << sh.file;
    for (const ScriptKey& k : s.keys()) {
      EXPECT_GT(k.position.x(), -0.1099) << sh.file << ":" << k.line;
      EXPECT_LT(k.position.x(), 0.1230) << sh.file << ":" << k.line;
      EXPECT_GT(k.position.y(), -0.0607) << sh.file << ":" << k.line;
      EXPECT_LT(k.position.y(), 0.0749) << sh.file << ":" << k.line;
      EXPECT_GT(k.position.z(), 0.0709 - 0.025) << sh.file << ":" << k.line;
      EXPECT_LT(k.position.z(), 0.0709 + 0.05) << sh.file << ":" << k.line;
      // The tool points straight down throughout.
      EXPECT_TRUE(k.orientation.coeffs().isApprox(Eigen::Quaterniond::Identity().coeffs()))
          << sh.file << ":" << k.line;
    }
  }
}

TEST(MockScript, ShippedScriptsDoWhatTheDocSays) {
  // Grasp-pull: the jaws close (0 → 1 over 0.3 s), stay closed through the 15 mm pull, open.
  const MockScript grasp = LoadShipped("grasp_pull.txt");
  EXPECT_EQ(grasp.At(2.0).jaw, 0.0);
  EXPECT_EQ(grasp.At(2.3).jaw, 1.0);
  EXPECT_NEAR(grasp.At(4.3).position.z() - grasp.At(2.3).position.z(), 0.015, 1e-9);
  EXPECT_EQ(grasp.At(5.3).jaw, 1.0);
  EXPECT_EQ(grasp.At(5.6).jaw, 0.0);
  EXPECT_NEAR(grasp.At(7.0).position.z() - grasp.At(5.6).position.z(), 0.03, 1e-9);
  // Incision: cut held through the 3 cm stroke along x at constant y, released at the end.
  const MockScript incision = LoadShipped("incision.txt");
  EXPECT_EQ(incision.At(0.5).buttons, 0U);
  for (double t = 1.5; t <= 3.5; t += 0.1) EXPECT_EQ(incision.At(t).buttons & 4U, 4U) << t;
  EXPECT_EQ(incision.At(4.5).buttons, 0U);
  const Eigen::Vector3d stroke = incision.At(3.5).position - incision.At(1.5).position;
  EXPECT_NEAR(stroke.x(), 0.030, 1e-9);
  EXPECT_EQ(stroke.y(), 0.0);
  // Palpation: three presses, each reaching its lowest point for 0.3 s.
  const MockScript palpate = LoadShipped("palpate.txt");
  int holds = 0;
  for (size_t i = 1; i < palpate.keys().size(); ++i) {
    const ScriptKey& a = palpate.keys()[i - 1];
    const ScriptKey& b = palpate.keys()[i];
    if (a.position == b.position && a.position.z() < 0.07) {
      ++holds;
      EXPECT_NEAR(b.time - a.time, 0.3, 1e-12);
    }
  }
  EXPECT_EQ(holds, 3);
  // The demo is the three parts in order, each shifted in time.
  const MockScript demo = LoadShipped("demo.txt");
  for (const auto& [part, offset] :
       {std::pair{&palpate, 0.0}, std::pair{&grasp, 7.0}, std::pair{&incision, 15.0}}) {
    for (const ScriptKey& k : part->keys()) {
      // Just after the key: k.time + offset may round below the demo's own key time.
      const ScriptSample d = demo.At(k.time + offset + 1e-9);
      EXPECT_EQ(demo.tools()[static_cast<size_t>(d.tool)], part->tools()[0]) << k.line;
      EXPECT_NEAR((d.position - k.position).norm(), 0.0, 1e-9) << part->tools()[0] << k.line;
      EXPECT_NEAR(d.jaw, k.jaw, 1e-6) << part->tools()[0] << k.line;
      EXPECT_EQ(d.buttons, k.buttons) << part->tools()[0] << k.line;
    }
  }
}

}  // namespace
}  // namespace somasim::haptic
