// Region outlines along pixel edges: exact areas, holes, islands, diagonal pixels, sides.
#include "slicestation/pipeline/region_outlines.hpp"

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

using namespace slicestation::pipeline;

namespace {

double ringArea(const std::vector<cv::Point2d>& r) {
    double a = 0;
    for (std::size_t i = 0; i < r.size(); ++i) {
        const cv::Point2d& p = r[i];
        const cv::Point2d& q = r[(i + 1) % r.size()];
        a += p.x * q.y - q.x * p.y;
    }
    return a / 2;
}

TEST(RegionOutlines, ASquareWithAHoleAndAnIslandInItGivesExactRingsAndAreas) {
    cv::Mat labels = cv::Mat::zeros(40, 40, CV_32S);
    labels(cv::Rect(5, 5, 20, 20)).setTo(7); // 400 px
    labels(cv::Rect(10, 10, 8, 8)).setTo(0); // hole of 64
    labels(cv::Rect(12, 12, 3, 3)).setTo(7); // island of 9 inside the hole
    labels(cv::Rect(30, 30, 4, 2)).setTo(9); // another region
    const auto out = regionOutlines(labels);
    ASSERT_EQ(out.size(), 2u);
    EXPECT_EQ(out[0].id, 7);
    EXPECT_EQ(out[0].pixels, 400 - 64 + 9);
    ASSERT_EQ(out[0].pieces.size(), 2u);
    double total = 0;
    int holes = 0;
    for (const auto& p : out[0].pieces) {
        total += p.areaPx;
        holes += int(p.holes.size());
        // Outer rings clockwise on the screen: positive shoelace with y down.
        EXPECT_GT(ringArea(p.outer), 0);
        for (const auto& h : p.holes)
            EXPECT_LT(ringArea(h), 0);
    }
    EXPECT_DOUBLE_EQ(total, 345);
    EXPECT_EQ(holes, 1);
    // The big piece's outer ring: the square's four corners on the pixels' edges.
    const auto& big = out[0].pieces[0].areaPx > 100 ? out[0].pieces[0] : out[0].pieces[1];
    ASSERT_EQ(big.outer.size(), 4u);
    for (const auto& p : big.outer) {
        EXPECT_TRUE(p.x == 4.5 || p.x == 24.5) << p;
        EXPECT_TRUE(p.y == 4.5 || p.y == 24.5) << p;
    }
    EXPECT_DOUBLE_EQ(ringArea(big.outer), 400);
    EXPECT_EQ(out[1].id, 9);
    EXPECT_DOUBLE_EQ(out[1].pieces.at(0).areaPx, 8);
}

TEST(RegionOutlines, DiagonalPixelsArePiecesOfTheirOwnAndTinyPiecesAreLeftOut) {
    cv::Mat labels = cv::Mat::zeros(10, 10, CV_32S);
    labels(cv::Rect(2, 2, 2, 2)).setTo(5);
    labels(cv::Rect(4, 4, 2, 2)).setTo(5); // touches the first at one corner only
    labels.at<std::int32_t>(8, 8) = 5;     // one pixel: under the 4 px minimum
    const auto out = regionOutlines(labels);
    ASSERT_EQ(out.size(), 1u);
    EXPECT_EQ(out[0].pixels, 9);
    ASSERT_EQ(out[0].pieces.size(), 2u);
    for (const auto& p : out[0].pieces) {
        EXPECT_EQ(p.outer.size(), 4u);
        EXPECT_DOUBLE_EQ(p.areaPx, 4);
    }
}

TEST(RegionOutlines, TheSideMapSplitsARegionAndTheAtlasMidlineSetsTheSide) {
    cv::Mat labels = cv::Mat::zeros(20, 20, CV_32S);
    labels(cv::Rect(2, 2, 16, 10)).setTo(3);
    // Atlas maps: x straight through; a coronal slice whose columns run along LR, 25 um each.
    cv::Mat mx(20, 20, CV_32F), my(20, 20, CV_32F);
    for (int y = 0; y < 20; ++y)
        for (int x = 0; x < 20; ++x) {
            mx.at<float>(y, x) = float(x);
            my.at<float>(y, x) = float(y);
        }
    SliceGeometry g;
    g.originUm = {1000, 0, 0};
    g.columnUm = {0, 0, 25};
    g.rowUm = {0, 25, 0};
    const cv::Mat side = atlasSideMap(mx, my, g, 10 * 25.0);
    EXPECT_EQ(side.at<std::uint8_t>(5, 9), 0);
    EXPECT_EQ(side.at<std::uint8_t>(5, 10), 1);
    const auto out = regionOutlines(labels, side);
    ASSERT_EQ(out.size(), 2u);
    EXPECT_EQ(out[0].side, 0);
    EXPECT_EQ(out[0].pixels, 8 * 10);
    EXPECT_EQ(out[1].side, 1);
    EXPECT_EQ(out[1].pixels, 8 * 10);
}

} // namespace
