#include "slicestation/pipeline/obb.hpp"

#include <gtest/gtest.h>

#include <cmath>

using namespace slicestation::pipeline;

TEST(OrientedBox, RecoversARotatedEllipse) {
    const double angle = 0.4;
    std::vector<cv::Point2f> pts;
    for (int i = 0; i < 2000; ++i) {
        const double t = 2 * CV_PI * i / 2000;
        const double u = 200 * std::cos(t), v = 80 * std::sin(t);
        pts.emplace_back(float(500 + u * std::cos(angle) - v * std::sin(angle)),
                         float(300 + u * std::sin(angle) + v * std::cos(angle)));
    }
    const OrientedBox b = orientedBox(pts);
    EXPECT_NEAR(b.centre.x, 500, 1.0);
    EXPECT_NEAR(b.centre.y, 300, 1.0);
    EXPECT_NEAR(std::abs(b.major[0] * std::cos(angle) + b.major[1] * std::sin(angle)), 1.0, 1e-3);
    EXPECT_NEAR(b.halfMajor, 200, 1.5);
    EXPECT_NEAR(b.halfMinor, 80, 1.5);
}

TEST(OrientedBox, InteriorPointsDoNotBiasTheAxes) {
    // A rectangle plus a dense cluster of "damage" points inside: the hull ignores them.
    std::vector<cv::Point2f> pts{{0, 0}, {400, 0}, {400, 100}, {0, 100}};
    for (int i = 0; i < 5000; ++i)
        pts.emplace_back(50.f + i % 50, 10.f + float(i % 80));
    const OrientedBox b = orientedBox(pts);
    EXPECT_NEAR(std::abs(b.major[0]), 1.0, 1e-4);
    EXPECT_NEAR(b.halfMajor, 200, 0.01);
    EXPECT_NEAR(b.centre.x, 200, 0.01);
}

TEST(OrientedBox, DegenerateInputGivesEmptyBox) {
    EXPECT_EQ(orientedBox({{1, 1}, {2, 2}}).halfMajor, 0);
}
