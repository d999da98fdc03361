#include "slicestation/pipeline/affine.hpp"
#include "slicestation/pipeline/icp.hpp"

#include <gtest/gtest.h>

#include <cmath>

using namespace slicestation::pipeline;

namespace {
/// An irregular closed curve with internal structure: a flower outline and an inner ellipse.
EdgePoints shape() {
    std::vector<cv::Point2f> raw;
    for (int i = 0; i < 3000; ++i) {
        const double t = 2 * CV_PI * i / 3000;
        const double r = 150 + 25 * std::cos(3 * t) + 10 * std::sin(5 * t);
        raw.emplace_back(float(300 + 1.3 * r * std::cos(t)), float(250 + r * std::sin(t)));
        raw.emplace_back(float(320 + 50 * std::cos(t)), float(230 + 30 * std::sin(t)));
    }
    return mlsEdgePoints(raw, 2.0f, 6.0f);
}
} // namespace

TEST(IcpAffine, RecoversAKnownAffineWithNormals) {
    const EdgePoints target = shape();
    const cv::Matx23d truth(1.05, 0.06, -12, -0.04, 0.95, 9); // source -> target
    const cv::Matx23d inv = invert(truth);
    EdgePoints source;
    for (size_t i = 0; i < target.size(); i += 2) {
        source.points.push_back(cv::Point2f(apply(inv, target.points[i])));
        source.normals.push_back(cv::Point2f(mapNormal(inv, target.normals[i])));
    }
    const PointGrid grid(target.points, 10.0f);
    IcpOptions o;
    const double h = 300;
    o.levels = {{10, h / 10}, {8, h / 20}, {6, h / 40}, {4, h / 80}};
    const cv::Matx23d start(1, 0, 0, 0, 1, 0); // identity: a few percent and ~15 px off
    const IcpResult r = icpAffine(source, target, grid, start, o);
    for (int k = 0; k < 200; ++k) {
        const cv::Point2d p = source.points[k * 7 % source.size()];
        EXPECT_LT(cv::norm(apply(r.targetFromSource, p) - apply(truth, p)), 0.5);
    }
    EXPECT_LT(r.rmsResidual, 1.0);
}

TEST(IcpAffine, FitAffineIsExactOnExactMatches) {
    const cv::Matx23d t(0.9, 0.1, 5, -0.2, 1.1, -3);
    std::vector<cv::Point2f> src{{0, 0}, {10, 0}, {0, 10}, {7, 3}, {2, 9}};
    std::vector<Match> m;
    for (int i = 0; i < 5; ++i)
        m.push_back({i, apply(t, src[i])});
    cv::Matx23d out;
    ASSERT_TRUE(fitAffine(src, m, out));
    for (int i = 0; i < 6; ++i)
        EXPECT_NEAR(out.val[i], t.val[i], 1e-9);
}

TEST(IcpAffine, FitAffineRefusesCollinearPoints) {
    std::vector<cv::Point2f> src{{0, 0}, {1, 1}, {2, 2}, {3, 3}};
    std::vector<Match> m;
    for (int i = 0; i < 4; ++i)
        m.push_back({i, {double(i), 0.0}});
    cv::Matx23d out(1, 2, 3, 4, 5, 6);
    EXPECT_FALSE(fitAffine(src, m, out));
    EXPECT_EQ(out(0, 1), 2);
}

TEST(IcpAffine, ConsistencyCheckDropsAnOutlierMatch) {
    EdgePoints target;
    std::vector<cv::Point2f> mp, mn;
    for (int i = 0; i < 50; ++i) {
        target.points.emplace_back(float(i), 0.f);
        target.normals.emplace_back(0.f, 1.f);
        mp.emplace_back(float(i), 1.f); // all displaced by (0,-1)
        mn.emplace_back(0.f, 1.f);
    }
    // One source point whose nearest targets lie far to the side.
    target.points.emplace_back(30.f, 20.f);
    target.normals.emplace_back(0.f, 1.f);
    mp.emplace_back(25.f, 17.f);
    mn.emplace_back(0.f, 1.f);
    const PointGrid grid(target.points, 4.0f);
    const auto kept = findMatches(mp, mn, target, grid, 6.0, 10.0, true);
    for (const auto& m : kept)
        EXPECT_NE(m.source, 50);
    EXPECT_GT(kept.size(), 40u);
}
