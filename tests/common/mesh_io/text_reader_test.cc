#include "common/mesh_io/text_reader.h"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "common/mesh_io/byte_reader.h"

namespace somasim::mesh_io {
namespace {

TEST(ParseNumbers, AcceptOnlyWholeTokens) {
  int64_t i = 0;
  EXPECT_TRUE(ParseInt64("42", &i));
  EXPECT_EQ(i, 42);
  EXPECT_TRUE(ParseInt64("+7", &i));
  EXPECT_EQ(i, 7);
  EXPECT_TRUE(ParseInt64("-3", &i));
  EXPECT_FALSE(ParseInt64("4x", &i));
  EXPECT_FALSE(ParseInt64("", &i));
  EXPECT_FALSE(ParseInt64("1.5", &i));
  EXPECT_FALSE(ParseInt64("99999999999999999999", &i));  // overflow
  double d = 0;
  EXPECT_TRUE(ParseDouble("1e-3", &d));
  EXPECT_EQ(d, 1e-3);
  EXPECT_TRUE(ParseDouble("-.5", &d));
  EXPECT_EQ(d, -0.5);
  EXPECT_TRUE(ParseDouble("nan", &d));
  EXPECT_TRUE(std::isnan(d));
  EXPECT_TRUE(ParseDouble("1e999", &d));  // overflow reads as infinity for the caller to refuse
  EXPECT_TRUE(std::isinf(d));
  EXPECT_FALSE(ParseDouble("1.0.0", &d));
  EXPECT_FALSE(ParseDouble("0x10", &d));
}

TEST(TextReader, TokensCarryTheirLineNumbers) {
  TextReader r("a b\n\n  c\r\nd", "f.txt");
  EXPECT_EQ(r.Token("x"), "a");
  EXPECT_EQ(r.token_location().line, 1);
  EXPECT_EQ(r.Token("x"), "b");
  EXPECT_EQ(r.Token("x"), "c");
  EXPECT_EQ(r.token_location().line, 3);
  EXPECT_EQ(r.Token("x"), "d");
  EXPECT_EQ(r.token_location().line, 4);
  EXPECT_TRUE(r.AtEnd());
  EXPECT_FALSE(r.TryToken().has_value());
}

TEST(TextReader, EndOfInputNamesWhatWasExpected) {
  TextReader r("12", "mesh.node");
  EXPECT_EQ(r.Int("count"), 12);
  try {
    r.Double("x coordinate");
    FAIL() << "no error";
  } catch (const MeshError& e) {
    EXPECT_EQ(e.kind(), MeshErrorKind::kSyntax);
    EXPECT_EQ(e.file(), "mesh.node");
    EXPECT_NE(std::string(e.what()).find("x coordinate"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("mesh.node:1"), std::string::npos) << e.what();
  }
}

TEST(TextReader, NonNumberIsRefusedWithTheToken) {
  TextReader r("\n\n3 x7", "a.msh");
  r.Int("n");
  try {
    r.Int("node id");
    FAIL();
  } catch (const MeshError& e) {
    EXPECT_EQ(e.where().line, 3);
    EXPECT_NE(std::string(e.what()).find("'x7'"), std::string::npos) << e.what();
  }
}

TEST(TextReader, LinesStripCarriageReturns) {
  TextReader r("one\r\ntwo\nthree", "f");
  EXPECT_EQ(r.Line("l"), "one");
  EXPECT_EQ(r.Line("l"), "two");
  EXPECT_EQ(r.Line("l"), "three");
  EXPECT_FALSE(r.TryLine().has_value());
  EXPECT_THROW(r.Line("header"), MeshError);
}

TEST(TextReader, EndOfLineRefusesTrailingTokens) {
  TextReader r("1 2 \n3 4 5\n", "f");
  r.Int("a");
  r.Int("b");
  EXPECT_NO_THROW(r.EndOfLine("b"));
  r.Int("c");
  r.Int("d");
  EXPECT_THROW(r.EndOfLine("d"), MeshError);
}

TEST(TextReader, AbsurdCountFailsBeforeAllocating) {
  TextReader r("1000000000000\n1 2 3\n", "big.node");
  const int64_t n = r.Int("count");
  try {
    r.CheckCount(n, 6, "nodes");
    FAIL();
  } catch (const MeshError& e) {
    EXPECT_EQ(e.kind(), MeshErrorKind::kCount);
    EXPECT_NE(std::string(e.what()).find("1000000000000"), std::string::npos);
  }
  EXPECT_THROW(r.CheckCount(-1, 1, "nodes"), MeshError);
  EXPECT_NO_THROW(r.CheckCount(1, 6, "nodes"));
  EXPECT_THROW(r.IntInRange("x", 2, 3), MeshError);
}

TEST(ByteReader, ReadsBothByteOrdersAndRefusesOverruns) {
  std::string bytes;
  AppendBinary<int32_t>(&bytes, 0x01020304, Endian::kBig);
  AppendBinary<double>(&bytes, -2.5, Endian::kLittle);
  ByteReader r(bytes, "b.stl", 100);
  EXPECT_EQ(r.Read<int32_t>(Endian::kBig, "i"), 0x01020304);
  EXPECT_EQ(r.Read<double>(Endian::kLittle, "d"), -2.5);
  try {
    r.Read<float>(Endian::kLittle, "x");
    FAIL();
  } catch (const MeshError& e) {
    EXPECT_EQ(e.where().byte, 112);  // base offset + bytes consumed
    EXPECT_NE(std::string(e.what()).find("byte 112"), std::string::npos) << e.what();
  }
  EXPECT_THROW(r.CheckCount(1, 1, "more"), MeshError);
}

TEST(FormatDouble, RoundTripsExactly) {
  for (double v :
       {0.1, 1.0 / 3.0, -1e-300, 6.02214076e23, 5e-324, std::numeric_limits<double>::max()}) {
    double back = 0;
    ASSERT_TRUE(ParseDouble(FormatDouble(v), &back)) << FormatDouble(v);
    EXPECT_EQ(back, v);
  }
}

}  // namespace
}  // namespace somasim::mesh_io
