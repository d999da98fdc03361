#include "slicestation/pipeline/edge_points.hpp"
#include "slicestation/pipeline/edges.hpp"

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

using namespace slicestation::pipeline;

namespace {
cv::Mat discImage(cv::Size size, cv::Point c, int r, float inside, float outside, double noise) {
    cv::Mat img(size, CV_32F, cv::Scalar(outside));
    cv::circle(img, c, r, cv::Scalar(inside), cv::FILLED, cv::LINE_AA);
    cv::Mat n(size, CV_32F);
    cv::RNG rng(3);
    rng.fill(n, cv::RNG::NORMAL, 0, noise);
    img += n;
    cv::min(cv::max(img, 0.0), 1.0, img);
    return img;
}
} // namespace

TEST(DominantEdges, FindsTheStrongCircleAndNotTheNoise) {
    const cv::Mat img = discImage({400, 300}, {200, 150}, 100, 0.8f, 0.1f, 0.04);
    const cv::Mat edges = dominantEdges(img);
    const auto px = edgePixels(edges);
    ASSERT_GT(px.size(), 400u); // circumference ~ 628 px
    int onCircle = 0;
    for (const auto& p : px)
        if (std::abs(std::hypot(p.x - 200, p.y - 150) - 100) < 3)
            ++onCircle;
    EXPECT_GT(onCircle, 0.95 * px.size());
}

TEST(DominantEdges, ThresholdSeparatesStrongFromWeakGradients) {
    // Many weak gradients (texture) and few strong ones: K must sit above the texture.
    cv::Mat mag(200, 200, CV_32F);
    cv::RNG rng(5);
    rng.fill(mag, cv::RNG::UNIFORM, 0.0, 10.0);
    mag(cv::Rect(0, 0, 200, 10)).setTo(200.0f);
    const double k = dominantEdgeThreshold(mag, DominantEdgeParams{});
    EXPECT_GT(k, 10.0);
    EXPECT_LE(k, 200.0);
}

TEST(DominantEdges, BlankImageGivesNoEdges) {
    const cv::Mat img(100, 100, CV_32F, cv::Scalar(0.5));
    EXPECT_EQ(cv::countNonZero(dominantEdges(img)), 0);
}

TEST(AtlasEdges, MarksOuterAndInnerBoundaries) {
    cv::Mat labels = cv::Mat::zeros(50, 50, CV_32S);
    labels(cv::Rect(10, 10, 30, 30)).setTo(1);
    labels(cv::Rect(25, 10, 15, 30)).setTo(2);
    const cv::Mat e = atlasEdges(labels);
    EXPECT_EQ(e.at<uchar>(20, 9), 255);  // outside -> region 1
    EXPECT_EQ(e.at<uchar>(20, 24), 255); // region 1 -> region 2
    EXPECT_EQ(e.at<uchar>(20, 15), 0);   // inside region 1
    const auto samples = labelBoundarySamples(labels);
    // Sub-pixel midpoints: the 1|2 boundary lies at x = 24.5.
    int mid = 0;
    for (const auto& s : samples)
        if (s.x == 24.5f)
            ++mid;
    EXPECT_EQ(mid, 30);
}
