// The viewer script (viewer/viewer_script.h): good scripts parse to their events; bad ones
// (a missing or wrong header, unknown moments and actions, bad numbers, NaN, wrong argument
// counts, out-of-range sizes, truncated lines, NUL bytes) are refused naming the line and
// what is wrong.
#include "viewer/viewer_script.h"

#include <gtest/gtest.h>

#include <fstream>
#include <string>

#include "tests/support/temp_files.h"

namespace somasim::viewer {
namespace {

using Action = ViewerEvent::Action;
using When = ViewerEvent::When;

TEST(ViewerScript, ParsesEveryActionWithItsMoment) {
  const std::vector<ViewerEvent> events = ParseViewerScript(
      "# a test script\n"
      "somasim-viewer-script 1   # the header\n"
      "\n"
      "frame 3 screenshot before.png\n"
      "sim 2.5 key n\n"
      "wall 0.25 key pagedown\r\n"
      "frame 0 resize 400 300\n"
      "frame 1 hide\n"
      "wall 1 show\n"
      "frame 2 iconify\n"
      "frame 2 recreate\n"
      "frame 4 drag -12 30\n"
      "frame 5 annotate check the hilum # not a comment here\n"
      "frame 6 quit\n"
      "frame 6 key enter\n",
      "test.txt");
  ASSERT_EQ(events.size(), 12u);
  EXPECT_EQ(events[11].action, Action::kKey);
  EXPECT_EQ(events[11].key, 13);
  EXPECT_EQ(events[0].when, When::kFrame);
  EXPECT_EQ(events[0].at, 3.0);
  EXPECT_EQ(events[0].action, Action::kScreenshot);
  EXPECT_EQ(events[0].text, "before.png");
  EXPECT_EQ(events[0].line, 4);
  EXPECT_EQ(events[1].when, When::kSim);
  EXPECT_EQ(events[1].at, 2.5);
  EXPECT_EQ(events[1].action, Action::kKey);
  EXPECT_EQ(events[1].key, 'n');
  EXPECT_EQ(events[2].when, When::kWall);
  EXPECT_EQ(events[2].action, Action::kSpecialKey);
  EXPECT_EQ(events[2].key, 105);  // GLUT_KEY_PAGE_DOWN
  EXPECT_EQ(events[3].action, Action::kResize);
  EXPECT_EQ(events[3].a, 400);
  EXPECT_EQ(events[3].b, 300);
  EXPECT_EQ(events[4].action, Action::kHide);
  EXPECT_EQ(events[5].action, Action::kShow);
  EXPECT_EQ(events[6].action, Action::kIconify);
  EXPECT_EQ(events[7].action, Action::kRecreate);
  EXPECT_EQ(events[8].action, Action::kDrag);
  EXPECT_EQ(events[8].a, -12);
  EXPECT_EQ(events[8].b, 30);
  EXPECT_EQ(events[9].action, Action::kAnnotate);
  EXPECT_EQ(events[9].text, "check the hilum # not a comment here");
  EXPECT_EQ(events[10].action, Action::kQuit);
}

TEST(ViewerScript, RefusesBadScriptsNamingTheLineAndTheReason) {
  struct Case {
    std::string text;
    std::string expected;  // a part of what()
  };
  const std::string h = "somasim-viewer-script 1\n";
  const Case cases[] = {
      {"", "s.txt:0: empty"},
      {"# only a comment\n", "empty"},
      {"frame 1 quit\n", "s.txt:1: the first line must be"},
      {"somasim-viewer-script 2\n", "format version \"2\" is not supported"},
      {"somasim-viewer-script\n", "format version \"\""},
      {h + "at 1 quit\n", "s.txt:2: \"at\": an event starts with frame N, sim T or wall S"},
      {h + "frame -1 quit\n", "frame \"-1\": not a count >= 0"},
      {h + "frame 1.5 quit\n", "frame \"1.5\""},
      {h + "frame\n", "frame \"\""},
      {h + "sim nan quit\n", "sim \"nan\": not a finite number"},
      {h + "wall inf quit\n", "wall \"inf\""},
      {h + "sim -2 quit\n", "sim \"-2\""},
      {h + "frame 1\n", "\"\": not an action"},
      {h + "frame 1 jump\n", "\"jump\": not an action"},
      {h + "frame 1 key\n", "key takes 1 argument, not 0"},
      {h + "frame 1 key ab\n", "key \"ab\": one printable character"},
      {h + "frame 1 screenshot\n", "screenshot takes 1 argument"},
      {h + "frame 1 resize 400\n", "resize takes 2 arguments, not 1"},
      {h + "frame 1 resize 8 300\n", "width and height are 16..8192"},
      {h + "frame 1 resize 400 nan\n", "width and height"},
      {h + "frame 1 drag 1 99999\n", "dx and dy are -8192..8192"},
      {h + "frame 1 quit now\n", "quit takes 0 arguments, not 1"},
      {h + "frame 1 annotate\n", "annotate needs the note's text"},
      {h + "frame 1 annotate " + std::string(1001, 'x') + "\n", "at most 1000 characters"},
      {h + "frame 1 quit\nframe 2 ke", "s.txt:3: \"ke\": not an action"},  // truncated
      {h + std::string("frame 1 q\0uit\n", 14), "a NUL byte"},
  };
  for (const Case& c : cases) {
    try {
      ParseViewerScript(c.text, "s.txt");
      ADD_FAILURE() << "accepted: " << c.text;
    } catch (const ViewerScriptError& e) {
      EXPECT_NE(std::string(e.what()).find(c.expected), std::string::npos)
          << "script: " << c.text << "\nsaid: " << e.what();
    }
  }
}

TEST(ViewerScript, LoadNamesAFileItCannotRead) {
  try {
    LoadViewerScript("/nonexistent/script.txt");
    ADD_FAILURE();
  } catch (const ViewerScriptError& e) {
    EXPECT_NE(std::string(e.what()).find("/nonexistent/script.txt:0: cannot open"),
              std::string::npos)
        << e.what();
  }
  const std::string file = somasim::testing::MakeTempDir("viewer_script") + "/script.txt";
  std::ofstream(file) << "somasim-viewer-script 1\nframe 1 quit\n";
  EXPECT_EQ(LoadViewerScript(file).size(), 1u);
}

}  // namespace
}  // namespace somasim::viewer
