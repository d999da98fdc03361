#include "slicestation/pipeline/affine.hpp"
#include "slicestation/pipeline/icp.hpp"

#include <gtest/gtest.h>
#include <opencv2/core/utility.hpp>

#include <algorithm>
#include <cmath>

using namespace slicestation::pipeline;

namespace {
/// OpenCV's thread count for one scope (matching and its consistency check run on its threads).
class Threads {
public:
    explicit Threads(int n) : before_(cv::getNumThreads()) { cv::setNumThreads(n); }
    ~Threads() { cv::setNumThreads(before_); }
    Threads(const Threads&) = delete;
    Threads& operator=(const Threads&) = delete;

private:
    int before_;
};

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

// The consistency check keeps exactly the matches the paper's rule keeps, stated here the slow
// way: for each match, the median x and y displacements (the element at position count / 2 of
// each sorted list) of the matches within 2 x distance of it, itself included, must lie within
// distance / 2 of its own displacement; a match with fewer than 3 such neighbours is dropped.
// Scattered points (neighbourhoods of 0 to several hundred) and clustered displacements with
// ties, at several distances, so that the incremental medians are checked on every path.
TEST(IcpAffine, ConsistencyCheckKeepsExactlyWhatTheRuleStatesKeeps) {
    // With one thread the visit is one stretch; with two it is cut in two, each with its own
    // sets.
    for (const int threads : {1, 2}) {
        SCOPED_TRACE("threads " + std::to_string(threads));
        const Threads scope(threads);
        cv::RNG rng(20261203);
        for (const double distance : {0.7, 2.0, 5.5, 13.0, 40.0}) {
            EdgePoints target;
            std::vector<cv::Point2f> mp, mn;
            for (int i = 0; i < 1500; ++i) {
                // Points on a few curves and some scattered ones, in a field of 60 x 40 distances.
                const bool onCurve = i % 5 != 0;
                const double t = rng.uniform(0.0, 2 * CV_PI);
                const double s = distance / 5;
                const cv::Point2f p =
                    onCurve ? cv::Point2f(float(s * (150 + (40 + 30 * (i % 3)) * std::cos(t))),
                                          float(s * (100 + (30 + 20 * (i % 3)) * std::sin(t))))
                            : cv::Point2f(float(s * rng.uniform(0.0, 300.0)),
                                          float(s * rng.uniform(0.0, 200.0)));
                // Normals in four classes 45 degrees apart: with 10 degrees allowed, a point
                // reaches only targets of its own class, so displacements vary from point to point.
                const double a = CV_PI / 4 * (i % 4);
                const cv::Point2f normal(float(std::cos(a)), float(std::sin(a)));
                mp.push_back(p);
                mn.push_back(normal);
                // Displacements: mostly one smooth motion, quantised so that ties occur, and a
                // share of outliers (not quantised).
                const double ox =
                    rng.uniform(0.0, 1.0) < 0.3 ? rng.uniform(-distance, distance) : 0;
                const double dx =
                    std::round(0.4 * distance * std::sin(p.y / (8 * distance))) / 4 + ox;
                const double dy =
                    std::round(4 * 0.1 * distance * std::cos(p.x / (10 * distance))) / 4;
                target.points.emplace_back(float(p.x + dx), float(p.y + dy));
                target.normals.push_back(normal);
            }
            const PointGrid grid(target.points, float(distance));
            const auto all =
                findMatches(mp, mn, target, grid, distance, 10.0, false, TargetRule::PointToLine);
            const auto kept =
                findMatches(mp, mn, target, grid, distance, 10.0, true, TargetRule::PointToLine);
            std::vector<int> expected;
            const float r = float(2 * distance);
            for (const Match& m : all) {
                const cv::Point2f at = mp[size_t(m.source)];
                std::vector<double> xs, ys;
                for (const Match& o : all) {
                    const cv::Point2f q = mp[size_t(o.source)];
                    const float ex = q.x - at.x, ey = q.y - at.y;
                    if (ex * ex + ey * ey <= r * r) {
                        xs.push_back(o.target.x - q.x);
                        ys.push_back(o.target.y - q.y);
                    }
                }
                if (xs.size() < 3)
                    continue;
                const size_t mid = xs.size() / 2;
                std::nth_element(xs.begin(), xs.begin() + long(mid), xs.end());
                std::nth_element(ys.begin(), ys.begin() + long(mid), ys.end());
                const double dx = (m.target.x - at.x) - xs[mid], dy = (m.target.y - at.y) - ys[mid];
                if (std::hypot(dx, dy) <= 0.5 * distance)
                    expected.push_back(m.source);
            }
            std::vector<int> got;
            for (const Match& m : kept)
                got.push_back(m.source);
            EXPECT_EQ(got, expected) << "distance " << distance;
            // The rule must have something to decide: some kept, some dropped.
            EXPECT_GT(got.size(), all.size() / 4) << "distance " << distance;
            EXPECT_LT(got.size(), all.size()) << "distance " << distance;
        }
    }
}

TEST(IcpAffine, MatchesAreTheSameWithAnyNumberOfThreads) {
    // 4000 points (over the size from which matching runs side by side): both target rules,
    // with and without the consistency check, one thread against two.
    cv::RNG rng(20261204);
    EdgePoints target;
    std::vector<cv::Point2f> mp, mn;
    for (int i = 0; i < 4000; ++i) {
        const double t = rng.uniform(0.0, 2 * CV_PI);
        const double r = 200 + 40 * (i % 4) + rng.gaussian(3.0);
        const cv::Point2f p(float(400 + r * std::cos(t)), float(300 + 0.8 * r * std::sin(t)));
        const cv::Point2f normal(float(std::cos(t)), float(std::sin(t)));
        mp.push_back(p);
        mn.push_back(normal);
        target.points.emplace_back(p.x + float(rng.gaussian(2.0)), p.y + float(rng.gaussian(2.0)));
        target.normals.push_back(normal);
    }
    const PointGrid grid(target.points, 6.0f);
    for (const TargetRule rule : {TargetRule::WeightedAverage, TargetRule::PointToLine})
        for (const bool check : {false, true}) {
            std::vector<Match> one, two;
            {
                const Threads scope(1);
                one = findMatches(mp, mn, target, grid, 6.0, 10.0, check, rule);
            }
            {
                const Threads scope(2);
                two = findMatches(mp, mn, target, grid, 6.0, 10.0, check, rule);
            }
            ASSERT_GT(one.size(), 1000u);
            ASSERT_EQ(one.size(), two.size());
            for (size_t k = 0; k < one.size(); ++k) {
                EXPECT_EQ(one[k].source, two[k].source);
                EXPECT_EQ(one[k].target, two[k].target); // exactly, not nearly
            }
        }
}
