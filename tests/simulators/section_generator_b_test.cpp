// The second generator family (generateSectionB): truth consistent with what is rendered,
// masks consistent with the damage, reproducible, bad options refused.
#include "slicestation/sim/builtin_atlas.hpp"
#include "slicestation/sim/section_generator_b.hpp"

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>

using namespace slicestation;

namespace {

const cv::Size kQuick{900, 660};

const cv::Mat& atlas() {
    static const cv::Mat plane = sim::builtinAtlasPlane(0.5);
    return plane;
}

sim::GeneratedSectionB generate(const sim::GeneratorOptionsB& o) {
    auto r = sim::generateSectionB(atlas(), core::Ontology{}, o);
    EXPECT_TRUE(r.ok()) << (r.ok() ? "" : r.error().message);
    return r.ok() ? std::move(r).value() : sim::GeneratedSectionB{};
}

sim::GeneratorOptionsB quick(std::uint64_t seed) {
    sim::GeneratorOptionsB o;
    o.seed = seed;
    o.imageSize = kQuick;
    return o;
}

bool sameBytes(const cv::Mat& a, const cv::Mat& b) {
    if (a.size() != b.size() || a.type() != b.type())
        return false;
    return cv::norm(a, b, cv::NORM_INF) == 0;
}

int atlasLabelAt(const cv::Point2d& atlasPx) {
    const long x = std::lround(atlasPx.x), y = std::lround(atlasPx.y);
    if (x < 0 || y < 0 || x >= atlas().cols || y >= atlas().rows)
        return -1;
    return atlas().at<std::int32_t>(int(y), int(x));
}

TEST(SectionGeneratorB, LandmarksLieInIntactTissueWithTheLabelTheRendererUsed) {
    for (std::uint64_t seed : {1u, 2u, 3u}) {
        auto o = quick(seed);
        o.damage.crack = o.damage.bite = true;
        const auto g = generate(o);
        ASSERT_EQ(g.truth.landmarks.size(), 200u);
        for (const auto& l : g.truth.landmarks) {
            const cv::Point p(int(l.image.x), int(l.image.y));
            const int rendered = g.truth.labelsInImage.at<std::int32_t>(p);
            EXPECT_GT(rendered, 0);
            EXPECT_NE(rendered, sim::kVentricularSystemsId);
            EXPECT_EQ(atlasLabelAt(l.atlas), rendered) << "seed " << seed << " at " << p;
            EXPECT_EQ(g.truth.tissueMask.at<std::uint8_t>(p), 255);
            EXPECT_EQ(g.truth.damageMask.at<std::uint8_t>(p), 0);
            EXPECT_FLOAT_EQ(float(l.atlas.x), g.truth.atlasX.at<float>(p));
            EXPECT_FLOAT_EQ(float(l.atlas.y), g.truth.atlasY.at<float>(p));
        }
    }
}

TEST(SectionGeneratorB, MapIsTheAffinePlusASmoothFoldFreeField) {
    const auto g = generate(quick(7));
    ASSERT_FALSE(g.image.empty());
    EXPECT_GE(g.minJacobian, 0.5);
    const auto& A = g.truth.affineAtlasFromImage;
    const double det = A(0, 0) * A(1, 1) - A(0, 1) * A(1, 0);
    EXPECT_GT(det, 0) << "a generated section is never mirrored";
    EXPECT_NEAR(g.imageUmPerPx, 25 * std::sqrt(det), 1e-9);
    // The non-linear part is visible (not zero) and bounded (a few atlas px).
    double maxOff = 0;
    for (int y = 0; y < kQuick.height; y += 7)
        for (int x = 0; x < kQuick.width; x += 7) {
            if (!g.truth.tissueMask.at<std::uint8_t>(y, x))
                continue;
            const cv::Point2d aff(A(0, 0) * x + A(0, 1) * y + A(0, 2),
                                  A(1, 0) * x + A(1, 1) * y + A(1, 2));
            maxOff = std::max(maxOff, cv::norm(aff - cv::Point2d(g.truth.atlasX.at<float>(y, x),
                                                                 g.truth.atlasY.at<float>(y, x))));
        }
    EXPECT_GT(maxOff, 1.0);
    EXPECT_LT(maxOff, 40.0);
    // The tissue lies inside the image: nothing on the border.
    const cv::Mat& t = g.truth.tissueMask;
    EXPECT_EQ(cv::countNonZero(t.row(0)) + cv::countNonZero(t.row(t.rows - 1)) +
                  cv::countNonZero(t.col(0)) + cv::countNonZero(t.col(t.cols - 1)),
              0);
}

TEST(SectionGeneratorB, EveryDamageKindIsPaintedAndMasked) {
    auto o = quick(11);
    o.damage = {true, true, true, true};
    const auto g = generate(o);
    ASSERT_EQ(g.truth.damage.size(), g.damageKinds.size());
    ASSERT_EQ(g.truth.damage.size(), 4u) << "crack, bite, fold and fragment each placed once";
    const auto intact = generate(quick(11));
    std::map<sim::DamageKindB, int> code{{sim::DamageKindB::Crack, 1},
                                         {sim::DamageKindB::Bite, 2},
                                         {sim::DamageKindB::Fold, 2},
                                         {sim::DamageKindB::Fragment, 3}};
    for (size_t i = 0; i < g.truth.damage.size(); ++i) {
        const auto& d = g.truth.damage[i];
        SCOPED_TRACE(std::string(sim::toString(g.damageKinds[i])));
        EXPECT_GT(d.areaPx, 20);
        ASSERT_GE(d.polygon.size(), 3u);
        // The region given was tissue before the damage and carries its code in the mask.
        cv::Mat region = cv::Mat::zeros(kQuick, CV_8U);
        std::vector<cv::Point> poly;
        for (const auto& p : d.polygon)
            poly.emplace_back(cvRound(p.x), cvRound(p.y));
        cv::fillPoly(region, std::vector<std::vector<cv::Point>>{poly}, cv::Scalar(255));
        const cv::Mat was = region & intact.truth.tissueMask;
        EXPECT_GT(cv::countNonZero(was), 0.5 * d.areaPx);
        const cv::Mat coded = (g.truth.damageMask == code[g.damageKinds[i]]) & region;
        EXPECT_GT(cv::countNonZero(coded), 0.5 * cv::countNonZero(was));
        if (g.damageKinds[i] == sim::DamageKindB::Crack ||
            g.damageKinds[i] == sim::DamageKindB::Bite) {
            // Removed: no tissue left where the crack or bite was (outline pixels aside).
            cv::Mat inner;
            cv::erode(region, inner, cv::Mat());
            EXPECT_EQ(cv::countNonZero(inner & g.truth.tissueMask &
                                       (g.truth.damageMask == code[g.damageKinds[i]])),
                      0);
        }
        if (g.damageKinds[i] == sim::DamageKindB::Fragment) {
            // The piece moved onto glass: tissue where it went, none where it was.
            const cv::Mat moved = (g.truth.damageMask == 3) & g.truth.tissueMask;
            EXPECT_GT(cv::countNonZero(moved), 0.8 * d.areaPx);
            EXPECT_NE(d.motion, cv::Matx23d(1, 0, 0, 0, 1, 0));
        }
    }
    // A crack is thin: a few px wide.
    cv::Mat crack = g.truth.damageMask == 1, dist;
    cv::distanceTransform(crack, dist, cv::DIST_L2, 3);
    double widest = 0;
    cv::minMaxLoc(dist, nullptr, &widest);
    EXPECT_LE(2 * widest, 8.0);
    // The landmarks avoid all of it.
    for (const auto& l : g.truth.landmarks)
        EXPECT_EQ(g.truth.damageMask.at<std::uint8_t>(cv::Point(int(l.image.x), int(l.image.y))),
                  0);
}

TEST(SectionGeneratorB, FoldDoublesTheBandBrighterInFluorescence) {
    auto o = quick(5);
    o.noise = 0;
    o.tiles = false;
    o.bubbles = 0;
    auto intactOptions = o;
    o.damage.fold = true;
    const auto g = generate(o);
    const auto intact = generate(intactOptions);
    ASSERT_EQ(g.damageKinds.size(), 1u);
    // The band: damage code 2 where tissue remains.
    const cv::Mat band = (g.truth.damageMask == 2) & g.truth.tissueMask & intact.truth.tissueMask;
    ASSERT_GT(cv::countNonZero(band), 20);
    EXPECT_GT(cv::mean(g.image, band)[0], 1.3 * cv::mean(intact.image, band)[0]);
    // The flap left its place: less tissue than before.
    EXPECT_LT(cv::countNonZero(g.truth.tissueMask), cv::countNonZero(intact.truth.tissueMask));
}

TEST(SectionGeneratorB, VentriclesAreEmptyAndStainsFollowTheRegions) {
    auto o = quick(3);
    o.noise = 0;
    o.texture = 0;
    o.tiles = false;
    o.bubbles = 0;
    const auto g = generate(o);
    const cv::Mat ventricle = g.truth.labelsInImage == sim::kVentricularSystemsId;
    ASSERT_GT(cv::countNonZero(ventricle), 0);
    EXPECT_EQ(cv::countNonZero(ventricle & g.truth.tissueMask), 0);
    // Without texture and noise each region is nearly uniform inside (away from its border,
    // where the optics blur it), and regions differ.
    std::map<int, std::vector<double>> values;
    cv::Mat inner;
    for (const auto& r : sim::builtinRegions()) {
        cv::erode(g.truth.labelsInImage == r.id, inner, cv::Mat(), {-1, -1}, 3);
        if (cv::countNonZero(inner) < 200)
            continue;
        cv::Scalar mean, sd;
        cv::meanStdDev(g.image, mean, sd, inner);
        EXPECT_LT(sd[0], 0.12 * mean[0] + 300) << r.name;
        values[r.id] = {mean[0]};
    }
    ASSERT_GE(values.size(), 5u);
    double lo = 1e9, hi = 0;
    for (const auto& [id, v] : values) {
        lo = std::min(lo, v[0]);
        hi = std::max(hi, v[0]);
    }
    EXPECT_GT(hi, 2 * lo) << "strong contrast between regions";
}

TEST(SectionGeneratorB, BrightfieldTissueIsDarkerThanGlass) {
    auto o = quick(4);
    o.brightfield = true;
    o.stain = sim::StainB::Nissl;
    const auto g = generate(o);
    ASSERT_EQ(g.image.type(), CV_8UC3);
    const cv::Scalar tissue = cv::mean(g.image, g.truth.tissueMask);
    const cv::Scalar glass = cv::mean(g.image, g.truth.tissueMask == 0);
    for (int c = 0; c < 3; ++c)
        EXPECT_LT(tissue[c], glass[c] - 20) << "channel " << c;
}

TEST(SectionGeneratorB, TemplateStainRendersTheTemplateThroughTheMap) {
    // A template with a smooth gradient: the rendering must follow it through the true map.
    cv::Mat templ(atlas().size(), CV_32F);
    for (int y = 0; y < templ.rows; ++y)
        for (int x = 0; x < templ.cols; ++x)
            templ.at<float>(y, x) = float(100 + x + 2 * y);
    auto o = quick(9);
    o.stain = sim::StainB::Template;
    o.templatePlane = templ;
    o.noise = 0;
    o.texture = 0;
    o.tiles = false;
    o.bubbles = 0;
    const auto g = generate(o);
    std::vector<double> a, b;
    cv::Mat inner;
    cv::erode(g.truth.tissueMask, inner, cv::Mat(), {-1, -1}, 3);
    for (int y = 0; y < kQuick.height; y += 5)
        for (int x = 0; x < kQuick.width; x += 5)
            if (inner.at<std::uint8_t>(y, x)) {
                a.push_back(g.image.at<std::uint16_t>(y, x));
                b.push_back(100 + g.truth.atlasX.at<float>(y, x) +
                            2 * g.truth.atlasY.at<float>(y, x));
            }
    ASSERT_GT(a.size(), 1000u);
    cv::Mat ca(a), cb(b), corr;
    cv::Scalar ma, sa, mb, sb;
    cv::meanStdDev(ca, ma, sa);
    cv::meanStdDev(cb, mb, sb);
    double c = 0;
    for (size_t i = 0; i < a.size(); ++i)
        c += (a[i] - ma[0]) * (b[i] - mb[0]);
    c /= double(a.size()) * sa[0] * sb[0];
    EXPECT_GT(c, 0.9);
}

TEST(SectionGeneratorB, SameSeedSameBytesOtherSeedOtherSection) {
    auto o = quick(21);
    o.damage.fragment = o.damage.fold = true;
    const auto a = generate(o), b = generate(o);
    EXPECT_TRUE(sameBytes(a.image, b.image));
    EXPECT_TRUE(sameBytes(a.truth.atlasX, b.truth.atlasX));
    EXPECT_TRUE(sameBytes(a.truth.damageMask, b.truth.damageMask));
    o.seed = 22;
    const auto c = generate(o);
    EXPECT_FALSE(sameBytes(a.image, c.image));
}

TEST(SectionGeneratorB, BadInputIsRefusedWithTheFieldNamed) {
    auto expectRefused = [](const cv::Mat& labels, const sim::GeneratorOptionsB& o,
                            const std::string& named) {
        auto r = sim::generateSectionB(labels, core::Ontology{}, o);
        ASSERT_FALSE(r.ok()) << named;
        EXPECT_EQ(r.error().code, core::ErrorCode::InvalidArgument);
        EXPECT_NE(r.error().message.find(named), std::string::npos) << r.error().message;
    };
    expectRefused(cv::Mat(), quick(1), "empty");
    expectRefused(cv::Mat(10, 10, CV_8U, cv::Scalar(3)), quick(1), "CV_32S");
    expectRefused(cv::Mat(10, 10, CV_32S, cv::Scalar(0)), quick(1), "no label");
    auto o = quick(1);
    o.imageSize = {200, 800};
    expectRefused(atlas(), o, "imageSize");
    o = quick(1);
    o.fillFraction = std::numeric_limits<double>::quiet_NaN();
    expectRefused(atlas(), o, "fillFraction");
    o = quick(1);
    o.noise = -1;
    expectRefused(atlas(), o, "noise");
    o = quick(1);
    o.landmarkCount = 100001;
    expectRefused(atlas(), o, "landmarkCount");
    o = quick(1);
    o.warpAmplitudeFrac = 0.5;
    expectRefused(atlas(), o, "warpAmplitudeFrac");
    o = quick(1);
    o.stain = sim::StainB::Template;
    expectRefused(atlas(), o, "templatePlane");
    o.templatePlane = cv::Mat(5, 5, CV_32F, cv::Scalar(1));
    expectRefused(atlas(), o, "templatePlane");
}

} // namespace
