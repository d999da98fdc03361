#include "slicestation/sim/builtin_atlas.hpp"

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <set>

using namespace slicestation;

namespace {

std::set<std::int32_t> labelsIn(const cv::Mat& plane) {
    std::set<std::int32_t> ids;
    for (int r = 0; r < plane.rows; ++r)
        for (int c = 0; c < plane.cols; ++c)
            ids.insert(plane.at<std::int32_t>(r, c));
    ids.erase(0);
    return ids;
}

std::set<std::int32_t> regionIds() {
    std::set<std::int32_t> ids;
    for (const auto& r : sim::builtinRegions())
        ids.insert(r.id);
    return ids;
}

} // namespace

TEST(BuiltinAtlas, RegionTableHasUniquePositiveAllenIds) {
    const auto& regions = sim::builtinRegions();
    EXPECT_GE(regions.size(), 10u);
    EXPECT_EQ(regionIds().size(), regions.size());
    for (const auto& r : regions) {
        EXPECT_GT(r.id, 0);
        EXPECT_FALSE(r.name.empty());
        EXPECT_FALSE(r.acronym.empty());
    }
    for (std::int32_t id : {315, 1080, 672, 549, 1097, 313, 803, 698, 703, 1009, 73})
        EXPECT_EQ(regionIds().count(id), 1u) << id;
}

TEST(BuiltinAtlas, DefaultPlaneIsALabelImageWithBackgroundBorder) {
    const cv::Mat plane = sim::builtinAtlasPlane();
    ASSERT_EQ(plane.type(), CV_32SC1);
    EXPECT_EQ(plane.size(), cv::Size(456, 320));
    const cv::Mat border = plane.clone();
    border(cv::Rect(1, 1, plane.cols - 2, plane.rows - 2)).setTo(0);
    EXPECT_EQ(cv::countNonZero(border), 0);
    EXPECT_TRUE(sim::builtinAtlasPlane(0.5, {0, 10}).empty());
}

TEST(BuiltinAtlas, PlanesAreExactlyMirrorSymmetric) {
    for (double ap : {0.0, 0.25, 0.5, 0.75, 1.0})
        for (cv::Size size : {cv::Size(456, 320), cv::Size(301, 211)}) {
            const cv::Mat plane = sim::builtinAtlasPlane(ap, size);
            cv::Mat mirrored;
            cv::flip(plane, mirrored, 1);
            EXPECT_EQ(cv::countNonZero(plane != mirrored), 0) << "ap " << ap << " " << size;
        }
}

TEST(BuiltinAtlas, EveryRegionAppearsAndNothingElse) {
    std::set<std::int32_t> seen;
    for (int i = 0; i <= 10; ++i) {
        const auto ids = labelsIn(sim::builtinAtlasPlane(i / 10.0));
        seen.insert(ids.begin(), ids.end());
    }
    EXPECT_EQ(seen, regionIds());
    // A mid-level plane alone shows nearly all of them.
    EXPECT_GE(labelsIn(sim::builtinAtlasPlane(0.5)).size(), 10u);
}

TEST(BuiltinAtlas, ShapeIsWiderThanTallAndFillsMostOfTheWidth) {
    const cv::Mat plane = sim::builtinAtlasPlane(0.5);
    const cv::Rect box = cv::boundingRect(plane > 0);
    const double aspect = double(box.width) / box.height;
    EXPECT_GT(aspect, 1.3);
    EXPECT_LT(aspect, 1.55);
    EXPECT_NEAR(double(box.width) / plane.cols, 0.85, 0.03);
    // One piece: the fissure and the ventricles do not cut the section apart.
    cv::Mat components;
    EXPECT_EQ(cv::connectedComponents(plane > 0, components, 8), 2);
}

TEST(BuiltinAtlas, ApChangesThePlaneSmoothly) {
    const cv::Mat a = sim::builtinAtlasPlane(0.50), b = sim::builtinAtlasPlane(0.52);
    const cv::Mat front = sim::builtinAtlasPlane(0.1), back = sim::builtinAtlasPlane(0.9);
    const int tissue = cv::countNonZero(a > 0);
    const int nearby = cv::countNonZero(a != b), far = cv::countNonZero(front != back);
    EXPECT_GT(nearby, 0);
    EXPECT_LT(nearby, tissue / 20);
    EXPECT_GT(far, tissue / 4);
    // The outline changes too, not only the inside.
    EXPECT_GT(cv::countNonZero((front > 0) != (back > 0)), 100);
}

TEST(BuiltinAtlas, BoundariesAreSmoothAtAnySize) {
    // Rendered larger, the same shape: the fraction of tissue agrees and region boundaries stay
    // thin curves (few pixels with a different neighbour relative to the area).
    const cv::Mat small = sim::builtinAtlasPlane(0.5);
    const cv::Mat large = sim::builtinAtlasPlane(0.5, {1368, 960});
    const double fracSmall = double(cv::countNonZero(small > 0)) / small.total();
    const double fracLarge = double(cv::countNonZero(large > 0)) / large.total();
    EXPECT_NEAR(fracSmall, fracLarge, 0.01);
    const auto edgePixels = [](const cv::Mat& m) {
        int n = 0;
        for (int r = 1; r < m.rows; ++r)
            for (int c = 1; c < m.cols; ++c)
                n += m.at<int>(r, c) != m.at<int>(r - 1, c) ||
                     m.at<int>(r, c) != m.at<int>(r, c - 1);
        return n;
    };
    // Boundary length scales with the size (x3), area with its square: no noisy boundaries.
    const double ratio = double(edgePixels(large)) / edgePixels(small);
    EXPECT_GT(ratio, 2.5);
    EXPECT_LT(ratio, 3.5);
}
