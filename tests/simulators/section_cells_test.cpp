// Labelled cells in generated sections (sim::CellOptions, issue 22): off by default and without
// effect on the rest of a section; placed in tissue, apart, with densities differing by region;
// not counted in damage; painted where they were placed; bad options refused.
#include "slicestation/sim/builtin_atlas.hpp"
#include "slicestation/sim/section_generator.hpp"
#include "slicestation/sim/section_generator_b.hpp"

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

#include <cmath>
#include <map>

using namespace slicestation;

namespace {

const cv::Mat& atlas() {
    static const cv::Mat plane = sim::builtinAtlasPlane(0.5);
    return plane;
}

sim::GeneratorOptions withCells(bool on) {
    sim::GeneratorOptions o;
    o.seed = 3;
    o.imageSize = {900, 660};
    o.cells.enabled = on;
    o.cells.diameterPx = 6;
    return o;
}

} // namespace

TEST(SectionCells, OffByDefaultAndTheRestOfTheSectionIsUnchanged) {
    auto off = sim::generateSection(atlas(), withCells(false));
    auto on = sim::generateSection(atlas(), withCells(true));
    ASSERT_TRUE(off.ok() && on.ok());
    EXPECT_TRUE(off->cells.empty());
    EXPECT_EQ(sim::GeneratorOptions{}.cells.enabled, false);
    ASSERT_GT(on->cells.size(), 100u);
    EXPECT_EQ(cv::norm(off->truth.atlasX, on->truth.atlasX, cv::NORM_INF), 0.0);
    EXPECT_EQ(cv::countNonZero(off->truth.tissueMask != on->truth.tissueMask), 0);
    ASSERT_EQ(off->truth.landmarks.size(), on->truth.landmarks.size());
    EXPECT_EQ(off->truth.landmarks[7].image, on->truth.landmarks[7].image);
    // The image differs only near cells: brighter there (fluorescence).
    cv::Mat near = cv::Mat::zeros(on->image.size(), CV_8U);
    for (const auto& c : on->cells)
        cv::circle(near, cv::Point(c.image), 8, cv::Scalar(255), cv::FILLED);
    cv::Mat a, b;
    off->image.convertTo(a, CV_32F);
    on->image.convertTo(b, CV_32F);
    // Away from cells the same picture, up to the exposure (the brightest cell sets it): the
    // two images correlate almost perfectly there.
    cv::Mat far = (near == 0) & on->truth.tissueMask;
    cv::Scalar ma, sa, mb, sb;
    cv::meanStdDev(a, ma, sa, far);
    cv::meanStdDev(b, mb, sb, far);
    cv::Mat prod = (a - ma[0]).mul(b - mb[0]);
    const double corr = cv::mean(prod, far)[0] / (sa[0] * sb[0]);
    EXPECT_GT(corr, 0.95);
    double atCells = 0;
    for (const auto& c : on->cells)
        atCells += b.at<float>(cv::Point(c.image)) - a.at<float>(cv::Point(c.image));
    EXPECT_GT(atCells / double(on->cells.size()), 0.0);
}

TEST(SectionCells, PlacedInTissueApartWithDensitiesByRegion) {
    auto g = sim::generateSection(atlas(), withCells(true));
    ASSERT_TRUE(g.ok());
    std::map<std::int32_t, int> perRegion;
    for (size_t i = 0; i < g->cells.size(); ++i) {
        const auto& c = g->cells[i];
        const cv::Point p(int(std::lround(c.image.x)), int(std::lround(c.image.y)));
        EXPECT_EQ(g->truth.labelsInImage.at<std::int32_t>(p), c.atlasId);
        EXPECT_GT(c.atlasId, 0);
        EXPECT_TRUE(c.counted); // no damage asked
        for (size_t j = i + 1; j < g->cells.size(); ++j)
            ASSERT_GE(cv::norm(c.image - g->cells[j].image), 0.8 * 6 - 1e-9);
        ++perRegion[c.atlasId];
    }
    // Densities differ by region: cells per tissue pixel vary by more than 2x between regions.
    double lo = 1e9, hi = 0;
    for (const auto& [id, n] : perRegion) {
        const int area = cv::countNonZero((g->truth.labelsInImage == id) & g->truth.tissueMask);
        if (area < 20000)
            continue;
        lo = std::min(lo, n / double(area));
        hi = std::max(hi, n / double(area));
    }
    EXPECT_GT(hi, 2 * lo);
}

TEST(SectionCells, CellsInDamageAreNotCountedInBothFamilies) {
    sim::GeneratorOptions o = withCells(true);
    o.damage.missing = o.damage.tear = true;
    auto g = sim::generateSection(atlas(), o);
    ASSERT_TRUE(g.ok());
    int notCounted = 0;
    for (const auto& c : g->cells) {
        const cv::Point p(int(std::lround(c.image.x)), int(std::lround(c.image.y)));
        const bool intact = g->truth.damageMask.at<std::uint8_t>(p) == 0 &&
                            g->truth.tissueMask.at<std::uint8_t>(p) != 0;
        EXPECT_EQ(c.counted, intact);
        notCounted += !c.counted;
    }
    EXPECT_GT(notCounted, 0);

    sim::GeneratorOptionsB ob;
    ob.seed = 4;
    ob.imageSize = {900, 660};
    ob.damage.bite = true;
    ob.brightfield = true;
    ob.cells.enabled = true;
    auto gb = sim::generateSectionB(atlas(), core::Ontology{}, ob);
    ASSERT_TRUE(gb.ok()) << gb.error().message;
    ASSERT_GT(gb->cells.size(), 100u);
    int notCountedB = 0;
    double darker = 0;
    for (const auto& c : gb->cells) {
        notCountedB += !c.counted;
        const cv::Vec3b v = gb->image.at<cv::Vec3b>(cv::Point(c.image));
        darker += v[0] + v[1] + v[2];
    }
    EXPECT_GT(notCountedB, 0);
    // Brightfield: cells absorb, darker than the tissue around on average.
    cv::Mat grey;
    cv::cvtColor(gb->image, grey, cv::COLOR_BGR2GRAY);
    EXPECT_LT(darker / 3 / double(gb->cells.size()), cv::mean(grey, gb->truth.tissueMask)[0]);
}

TEST(SectionCells, BadCellOptionsAreRefusedOnlyWhenEnabled) {
    sim::GeneratorOptions o = withCells(true);
    o.cells.diameterPx = 0.5;
    auto r = sim::generateSection(atlas(), o);
    ASSERT_FALSE(r.ok());
    EXPECT_NE(r.error().message.find("cells.diameterPx"), std::string::npos);
    o.cells.enabled = false;
    EXPECT_TRUE(sim::generateSection(atlas(), o).ok());
    sim::GeneratorOptionsB ob;
    ob.cells.enabled = true;
    ob.cells.contrast = 50;
    auto rb = sim::generateSectionB(atlas(), core::Ontology{}, ob);
    ASSERT_FALSE(rb.ok());
    EXPECT_NE(rb.error().message.find("cells.contrast"), std::string::npos);
}
