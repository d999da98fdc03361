#include "slicestation/daemon/cli/points_csv.hpp"

#include <gtest/gtest.h>

using namespace slicestation;
using daemon::parsePointsCsv;

TEST(PointsCsv, ParsesPointsInOrder) {
    auto r = parsePointsCsv("x,y\n1,2\r\n 3.5 , -4e1\n\n7,8,extra\n");
    ASSERT_TRUE(r.ok()) << r.error().message;
    ASSERT_EQ(r->size(), 3u);
    EXPECT_EQ((*r)[0], cv::Point2d(1, 2));
    EXPECT_EQ((*r)[1], cv::Point2d(3.5, -40));
    EXPECT_EQ((*r)[2], cv::Point2d(7, 8));
}

TEST(PointsCsv, HeaderOnlyIsAnEmptyList) {
    auto r = parsePointsCsv("\xEF\xBB\xBFx,y\n");
    ASSERT_TRUE(r.ok());
    EXPECT_TRUE(r->empty());
}

TEST(PointsCsv, MalformedInputNamesTheLine) {
    struct Case {
        const char* text;
        const char* needle;
    };
    for (const Case& c :
         {Case{"", "empty"}, Case{"a,b\n1,2\n", "line 1"}, Case{"x,y\n1,2\n3\n", "line 3"},
          Case{"x,y\n1,zz\n", "y is not a number"}, Case{"x,y\n1,2\nnan,3\n", "line 3"},
          Case{"x,y\n1e999,2\n", "line 2"}, Case{"x,y\n,2\n", "x is not a number"}}) {
        auto r = parsePointsCsv(c.text);
        ASSERT_FALSE(r.ok()) << c.text;
        EXPECT_EQ(r.error().code, core::ErrorCode::InvalidArgument);
        EXPECT_NE(r.error().message.find(c.needle), std::string::npos) << r.error().message;
    }
}

TEST(PointsCsv, MissingFileIsNotFound) {
    auto r = daemon::readPointsCsv("/nonexistent/points.csv");
    ASSERT_FALSE(r.ok());
    EXPECT_EQ(r.error().code, core::ErrorCode::NotFound);
}

TEST(PointsCsv, QuotedFieldsAndBrokenQuotingFollowTheCoreReader) {
    auto r = parsePointsCsv("\"x\",\"y\",\"note, with comma\"\r\n\"1.5\",2,\"a \"\"b\"\"\"\r\n");
    ASSERT_TRUE(r.ok()) << r.error().message;
    ASSERT_EQ(r->size(), 1u);
    EXPECT_EQ((*r)[0], cv::Point2d(1.5, 2));
    auto open = parsePointsCsv("x,y\n1,\"2\n");
    ASSERT_FALSE(open.ok());
    EXPECT_EQ(open.error().code, core::ErrorCode::InvalidArgument);
    EXPECT_NE(open.error().message.find("line 2, field 2: quoted field is never closed"),
              std::string::npos)
        << open.error().message;
}
