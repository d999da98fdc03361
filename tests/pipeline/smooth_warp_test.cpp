#include "slicestation/pipeline/smooth_warp.hpp"

#include "slicestation/pipeline/affine.hpp"

#include <gtest/gtest.h>

#include <cmath>

using namespace slicestation::pipeline;

namespace {

/// Points and normals on a few closed curves and lines inside a 1000 x 700 domain: a section's
/// outline and internal boundaries in spirit.
EdgePoints curves() {
    EdgePoints e;
    auto add = [&](cv::Point2d p, cv::Point2d tangent) {
        const double len = std::hypot(tangent.x, tangent.y);
        e.points.emplace_back(float(p.x), float(p.y));
        e.normals.emplace_back(float(-tangent.y / len), float(tangent.x / len));
    };
    for (int i = 0; i < 900; ++i) { // outline
        const double t = 2 * CV_PI * i / 900;
        add({500 + 420 * std::cos(t), 350 + 300 * std::sin(t)}, {-std::sin(t), std::cos(t)});
    }
    for (int k = 0; k < 3; ++k) // inner ellipses
        for (int i = 0; i < 300; ++i) {
            const double t = 2 * CV_PI * i / 300;
            const cv::Point2d c(260 + 240 * k, 330 + 40 * (k % 2));
            add({c.x + 90 * std::cos(t), c.y + 140 * std::sin(t)}, {-std::sin(t), std::cos(t)});
        }
    for (int i = 0; i < 500; ++i) { // a slanted line across
        const double t = i / 499.0;
        add({150 + 700 * t, 150 + 400 * t}, {700, 400});
    }
    return e;
}

/// A smooth deformation of about 4 px amplitude with features half the domain across.
cv::Point2d bend(cv::Point2d p) {
    return {4.0 * std::sin(p.y / 700 * CV_PI) + 2.0 * std::cos(p.x / 1000 * 2 * CV_PI),
            -3.0 * std::sin(p.x / 1000 * CV_PI) + 1.5 * std::sin(p.y / 700 * 2 * CV_PI)};
}

/// The curves as a section, at half scale and shifted into the atlas frame, and the atlas edges
/// they are matched to: the section points through that affine and the bend.
struct BentSection {
    EdgePoints src = curves();
    cv::Matx23d affine{0.5, 0, 20, 0, 0.5, 10};
    EdgePoints target;
    PointGrid grid{{}, 10.0f};
    BentSection() {
        for (size_t i = 0; i < src.size(); ++i) {
            const cv::Point2d p(src.points[i]);
            target.points.emplace_back(apply(affine, p) + bend(p));
            target.normals.push_back(src.normals[i]);
        }
        grid = PointGrid(target.points, 10.0f);
    }
    SmoothWarp fit(const SmoothWarpOptions& o) const {
        return fitSmoothWarp({1000, 700}, affine, {{&src, &target, &grid, 1.0}}, 5.0, o);
    }
};

double rmsError(const EdgePoints& src, const cv::Matx23d& affine, const DisplacementField& f) {
    double ss = 0;
    for (const cv::Point2f& q : src.points) {
        const cv::Point2d p(q);
        const cv::Point2d truth = apply(affine, p) + bend(p);
        const cv::Point2d got = apply(affine, p) + f.at(p);
        ss += std::pow(cv::norm(truth - got), 2);
    }
    return std::sqrt(ss / double(src.size()));
}

} // namespace

TEST(SmoothWarp, RecoversASmoothDeformationOfEdgesFromPointToLineMatches) {
    // The atlas frame: the section scaled by 0.5 and shifted; the targets are the deformed
    // section points, densely resampled so point-to-line matches exist.
    const BentSection b;
    SmoothWarpOptions o;
    o.levels = {{12, 20, 3}, {6, 15, 3}, {3, 10, 3}};
    const SmoothWarp sw = b.fit(o);
    ASSERT_FALSE(sw.field.empty());
    const double before = rmsError(b.src, b.affine, DisplacementField());
    const double after = rmsError(b.src, b.affine, sw.field);
    EXPECT_GT(before, 2.0);
    // The default stiffness recovers most of it; a softer membrane follows the matches closer.
    EXPECT_LT(after, 0.5 * before) << "before " << before << " after " << after;
    EXPECT_LT(sw.rmsAfter, sw.rmsBefore);
    o.stiffness = 0.002;
    EXPECT_LT(rmsError(b.src, b.affine, b.fit(o).field), 0.3 * before);
}

TEST(SmoothWarp, ALevelSteersWithItsPointsThinnedToAnEighthOfItsReach) {
    // One loose level (12 atlas px, the section at half scale): thinned to a point per 3 section
    // px the curves (1.6 - 2.5 px apart) give fewer matches, and the field still recovers the
    // bend as well as with every point.
    const BentSection b;
    SmoothWarpOptions o;
    o.levels = {{12, 20, 3}};
    o.thinning = 0;
    const SmoothWarp every = b.fit(o);
    o.thinning = 0.125;
    const SmoothWarp thinned = b.fit(o);
    EXPECT_LT(thinned.matches, 0.8 * every.matches);
    EXPECT_GT(thinned.matches, 0.3 * every.matches);
    const double before = rmsError(b.src, b.affine, DisplacementField());
    const double withEvery = rmsError(b.src, b.affine, every.field);
    const double withThinned = rmsError(b.src, b.affine, thinned.field);
    EXPECT_LT(withEvery, 0.5 * before);
    EXPECT_LT(withThinned, withEvery + 0.1 * before) << withEvery << " " << withThinned;
}

TEST(SmoothWarp, StaysZeroWithoutMatchesAndAddsFields) {
    const EdgePoints src = curves();
    EdgePoints far;
    far.points = {cv::Point2f(5000, 5000)};
    far.normals = {cv::Point2f(1, 0)};
    const PointGrid grid(far.points, 10.0f);
    SmoothWarpOptions o;
    o.levels = {{5, 10, 2}};
    const SmoothWarp sw = fitSmoothWarp({1000, 700}, cv::Matx23d(1, 0, 0, 0, 1, 0),
                                        {{&src, &far, &grid, 1.0}}, 5.0, o);
    EXPECT_TRUE(sw.field.empty());
    EXPECT_EQ(sw.matches, 0);

    const DisplacementField a(cv::Mat(3, 3, CV_32F, cv::Scalar(1.0f)),
                              cv::Mat(3, 3, CV_32F, cv::Scalar(-2.0f)), 10.0);
    const DisplacementField b(cv::Mat(2, 2, CV_32F, cv::Scalar(0.5f)),
                              cv::Mat(2, 2, CV_32F, cv::Scalar(0.25f)), 20.0);
    const DisplacementField sum = addFields(a, b);
    EXPECT_NEAR(sum.at({15, 5}).x, 1.5, 1e-6);
    EXPECT_NEAR(sum.at({15, 5}).y, -1.75, 1e-6);
    EXPECT_NEAR(addFields(DisplacementField(), b).at({0, 0}).x, 0.5, 1e-6);
}
