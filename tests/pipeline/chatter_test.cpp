#include "slicestation/pipeline/chatter.hpp"

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

#include <cmath>

using namespace slicestation::pipeline;

namespace {

/// A section 500 px wide: an ellipse of tissue at 0.6 with a cell-like texture (blurred noise,
/// no period), glass at 0.05.
struct Section {
    cv::Mat tissue, grey;
    Section() {
        const cv::Size size(600, 400);
        tissue = cv::Mat::zeros(size, CV_8U);
        cv::ellipse(tissue, {300, 200}, {250, 160}, 0, 0, 360, cv::Scalar(255), cv::FILLED);
        cv::Mat noise(size, CV_32F);
        cv::RNG rng(7);
        rng.fill(noise, cv::RNG::NORMAL, 0, 0.25);
        cv::GaussianBlur(noise, noise, cv::Size(), 1.5);
        grey = cv::Mat(size, CV_32F, cv::Scalar(0.05));
        cv::Mat level = 0.6 * (1 + noise);
        level.copyTo(grey, tissue);
    }
    /// The thickness swinging by `swing` (0.3: 30% below and above) with `period` px along x in
    /// the strip x0 <= x < x0 + width (and y0 <= y < y1).
    void chatter(double period, double swing, int x0, int width, int y0 = 0, int y1 = 400) {
        for (int y = y0; y < y1; ++y)
            for (int x = x0; x < x0 + width; ++x)
                if (tissue.at<uchar>(y, x))
                    grey.at<float>(y, x) *= float(1 + swing * std::sin(2 * CV_PI * x / period));
    }
};

} // namespace

TEST(Chatter, ParallelBandsOfThicknessAcrossAStripAreChatter) {
    Section s;
    s.chatter(10, 0.3, 200, 150); // a period of 2% of the width
    const DamageParams p;
    const std::vector<DamageRegion> found = chatterBands(s.grey, s.tissue, 500, p);
    ASSERT_EQ(found.size(), 1u);
    const DamageRegion& d = found[0];
    EXPECT_EQ(d.kind, DamageKind::Chatter);
    EXPECT_NEAR(d.thicknessPx, 10, 1.5) << "the period";
    EXPECT_NEAR(d.levelShare, 0.3, 0.12) << "the swing";
    EXPECT_GT(d.share, 0.1);
    // Over the strip.
    cv::Mat region = cv::Mat::zeros(s.grey.size(), CV_8U);
    std::vector<cv::Point> poly;
    for (const cv::Point2f& q : d.polygon)
        poly.emplace_back(cvRound(q.x), cvRound(q.y));
    cv::fillPoly(region, std::vector<std::vector<cv::Point>>{poly}, cv::Scalar(255));
    const cv::Moments m = cv::moments(region, true);
    EXPECT_NEAR(m.m10 / m.m00, 275, 40);
    EXPECT_NE(damageSummary(found).find("1 chatter"), std::string::npos) << damageSummary(found);
    // Flagged on its own.
    std::vector<DamageRegion> decided = found;
    EXPECT_EQ(decideDamage(decided, 500, p).verdict, DamageVerdict::Damaged);
}

TEST(Chatter, TextureWeakBandsOtherPeriodsAndOffAreNot) {
    const DamageParams p;
    // Tissue's own texture has no single period.
    Section plain;
    EXPECT_TRUE(chatterBands(plain.grey, plain.tissue, 500, p).empty());
    // A swing of 4%: under chatterSwing.
    Section weak;
    weak.chatter(10, 0.04, 200, 150);
    EXPECT_TRUE(chatterBands(weak.grey, weak.tissue, 500, p).empty());
    // Bands 30 px apart (6% of the width): wider than a knife's chatter, such as layers.
    Section wide;
    wide.chatter(30, 0.3, 150, 300);
    EXPECT_TRUE(chatterBands(wide.grey, wide.tissue, 500, p).empty());
    // A patch of bands covering fewer than chatterTiles tiles: a local pattern (a striated
    // structure), not the knife.
    Section narrow;
    narrow.chatter(10, 0.3, 270, 60, 170, 230);
    EXPECT_TRUE(chatterBands(narrow.grey, narrow.tissue, 500, p).empty());
    // Off.
    Section strong;
    strong.chatter(10, 0.3, 200, 150);
    DamageParams off = p;
    off.chatterTiles = 0;
    EXPECT_TRUE(chatterBands(strong.grey, strong.tissue, 500, off).empty());
}
