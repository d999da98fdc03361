#include "slicestation/pipeline/edge_points.hpp"
#include "slicestation/pipeline/point_grid.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <random>

using namespace slicestation::pipeline;

TEST(MlsEdgePoints, NormalsOfANoisyCircleAreRadialAndPointsAreSmoothed) {
    std::mt19937 rng(1);
    std::normal_distribution<float> noise(0.f, 0.7f);
    std::vector<cv::Point2f> raw;
    for (int i = 0; i < 4000; ++i) {
        const double t = 2 * CV_PI * i / 4000;
        raw.emplace_back(float(300 + 150 * std::cos(t)) + noise(rng),
                         float(300 + 150 * std::sin(t)) + noise(rng));
    }
    const EdgePoints e = mlsEdgePoints(raw, 2.0f, 8.0f);
    ASSERT_GT(e.size(), 250u);
    double worstDeg = 0, rawErr = 0, mlsErr = 0;
    for (size_t i = 0; i < e.size(); ++i) {
        const cv::Point2f d = e.points[i] - cv::Point2f(300, 300);
        const double r = std::hypot(d.x, d.y);
        const double c = std::abs(d.x * e.normals[i].x + d.y * e.normals[i].y) / r;
        worstDeg = std::max(worstDeg, std::acos(std::min(1.0, c)) * 180 / CV_PI);
        mlsErr += std::abs(r - 150);
    }
    for (const auto& p : raw)
        rawErr += std::abs(std::hypot(p.x - 300, p.y - 300) - 150);
    EXPECT_LT(worstDeg, 6.0);
    EXPECT_LT(mlsErr / double(e.size()), 0.5 * rawErr / double(raw.size()));
}

TEST(MlsEdgePoints, IsolatedSpecksAreDropped) {
    const std::vector<cv::Point2f> raw{{10, 10}, {100, 100}, {200, 50}};
    EXPECT_EQ(mlsEdgePoints(raw, 1.0f, 5.0f).size(), 0u);
}

TEST(PointGrid, FindsExactlyThePointsWithinTheRadius) {
    std::vector<cv::Point2f> pts;
    for (int y = 0; y < 20; ++y)
        for (int x = 0; x < 20; ++x)
            pts.emplace_back(float(x), float(y));
    const PointGrid g(pts, 3.0f);
    int n = 0;
    g.forEachWithin({10, 10}, 2.0f, [&](int, float d2) {
        EXPECT_LE(d2, 4.0f);
        ++n;
    });
    EXPECT_EQ(n, 13); // lattice points within radius 2
    EXPECT_EQ(g.nearest({4.2f, 7.9f}, 1.0f), 8 * 20 + 4);
    EXPECT_EQ(g.nearest({-5, -5}, 1.0f), -1);
}
