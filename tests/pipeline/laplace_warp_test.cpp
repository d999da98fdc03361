#include "slicestation/pipeline/laplace_warp.hpp"

#include <gtest/gtest.h>

#include <cmath>

using namespace slicestation::pipeline;

TEST(LaplaceWarp, ConstantBoundaryGivesConstantField) {
    std::vector<cv::Point2d> pts, disp;
    for (int i = 0; i < 400; ++i) {
        const double t = 2 * CV_PI * i / 400;
        pts.emplace_back(500 + 300 * std::cos(t), 400 + 250 * std::sin(t));
        disp.emplace_back(3.0, -2.0);
    }
    const auto f = solveLaplaceWarp({1000, 800}, pts, disp);
    for (const cv::Point2d p :
         {cv::Point2d(500, 400), cv::Point2d(10, 10), cv::Point2d(990, 790)}) {
        EXPECT_NEAR(f.at(p).x, 3.0, 0.05);
        EXPECT_NEAR(f.at(p).y, -2.0, 0.05);
    }
}

TEST(LaplaceWarp, InterpolatesBetweenTwoCurvesAndHoldsTheConditions) {
    // u = 0 on the line x = 200, u = 10 on x = 800: between them the harmonic solution is linear.
    std::vector<cv::Point2d> pts, disp;
    for (int y = 0; y <= 600; y += 2) {
        pts.emplace_back(200, y);
        disp.emplace_back(0, 0);
        pts.emplace_back(800, y);
        disp.emplace_back(10, 0);
    }
    LaplaceOptions o;
    o.sweepsPerLevel = 80;
    const auto f = solveLaplaceWarp({1000, 600}, pts, disp, o);
    EXPECT_NEAR(f.at({200, 300}).x, 0.0, 1e-4);
    EXPECT_NEAR(f.at({800, 300}).x, 10.0, 1e-4);
    EXPECT_NEAR(f.at({500, 300}).x, 5.0, 0.3);
    EXPECT_NEAR(f.at({350, 100}).x, 2.5, 0.3);
    EXPECT_NEAR(f.at({900, 300}).x, 10.0, 0.3); // Neumann border beyond the last curve
}

TEST(LaplaceWarp, NoPointsGivesAnEmptyZeroField) {
    const auto f = solveLaplaceWarp({100, 100}, {}, {});
    EXPECT_TRUE(f.empty());
    EXPECT_EQ(f.at({5, 5}), cv::Point2d(0, 0));
}
