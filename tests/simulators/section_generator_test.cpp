#include "slicestation/sim/builtin_atlas.hpp"
#include "slicestation/sim/section_generator.hpp"

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <functional>
#include <limits>
#include <map>
#include <string>

using namespace slicestation;

namespace {

/// Smaller than the default, for tests where the size does not matter: keeps the suite quick.
const cv::Size kQuickSize{1000, 740};

const cv::Mat& atlas() {
    static const cv::Mat plane = sim::builtinAtlasPlane(0.5);
    return plane;
}

sim::GeneratedSection generate(const sim::GeneratorOptions& o, const cv::Mat& labels = atlas()) {
    auto r = sim::generateSection(labels, o);
    EXPECT_TRUE(r.ok()) << (r.ok() ? "" : r.error().message);
    return r.ok() ? std::move(r).value() : sim::GeneratedSection{};
}

bool sameBytes(const cv::Mat& a, const cv::Mat& b) {
    if (a.size() != b.size() || a.type() != b.type())
        return false;
    for (int r = 0; r < a.rows; ++r)
        if (!std::equal(a.ptr(r), a.ptr(r) + a.cols * a.elemSize(), b.ptr(r)))
            return false;
    return true;
}

double medianOf(const cv::Mat& image, const cv::Mat& mask) {
    std::vector<float> v;
    cv::Mat f;
    image.convertTo(f, CV_32F);
    for (int r = 0; r < f.rows; ++r)
        for (int c = 0; c < f.cols; ++c)
            if (mask.at<std::uint8_t>(r, c))
                v.push_back(f.at<float>(r, c));
    if (v.empty())
        return std::numeric_limits<double>::quiet_NaN();
    std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
    return v[v.size() / 2];
}

cv::Mat eroded(const cv::Mat& mask, int radius) {
    cv::Mat out;
    cv::erode(mask, out,
              cv::getStructuringElement(cv::MORPH_ELLIPSE, {2 * radius + 1, 2 * radius + 1}));
    return out;
}

cv::Mat dilated(const cv::Mat& mask, int radius) {
    cv::Mat out;
    cv::dilate(mask, out,
               cv::getStructuringElement(cv::MORPH_ELLIPSE, {2 * radius + 1, 2 * radius + 1}));
    return out;
}

/// Tissue before damage: the labels seen through the map, without ventricles.
cv::Mat intactTissue(const sim::GroundTruth& t) {
    return (t.labelsInImage > 0) & (t.labelsInImage != 73);
}

const sim::DamageRegion* findDamage(const sim::GroundTruth& t, sim::DamageKind kind) {
    for (const auto& d : t.damage)
        if (d.kind == kind)
            return &d;
    return nullptr;
}

/// A tenth of the way from the glass around the section (beyond 20 px) to its tissue (3 px
/// inside): where a hole that shows the slide must lie below.
double glassLine(const sim::GeneratedSection& g) {
    const double glass = medianOf(g.image, ~dilated(g.truth.tissueMask, 20));
    const double tissue = medianOf(g.image, eroded(g.truth.tissueMask, 3));
    return glass + 0.1 * (tissue - glass);
}

} // namespace

TEST(SectionGenerator, SameSeedGivesIdenticalBytesOtherSeedDiffers) {
    sim::GeneratorOptions o;
    o.seed = 7;
    o.damage = {true, true, true};
    const auto a = generate(o), b = generate(o);
    EXPECT_TRUE(sameBytes(a.image, b.image));
    EXPECT_TRUE(sameBytes(a.truth.atlasX, b.truth.atlasX));
    EXPECT_TRUE(sameBytes(a.truth.atlasY, b.truth.atlasY));
    EXPECT_TRUE(sameBytes(a.truth.damageMask, b.truth.damageMask));
    ASSERT_EQ(a.truth.landmarks.size(), b.truth.landmarks.size());
    for (size_t i = 0; i < a.truth.landmarks.size(); ++i) {
        EXPECT_EQ(a.truth.landmarks[i].image, b.truth.landmarks[i].image);
        EXPECT_EQ(a.truth.landmarks[i].atlas, b.truth.landmarks[i].atlas);
    }
    o.seed = 8;
    const auto c = generate(o);
    EXPECT_FALSE(sameBytes(a.image, c.image));
    EXPECT_FALSE(sameBytes(a.truth.atlasX, c.truth.atlasX));
}

TEST(SectionGenerator, OutputTypesFollowTheStain) {
    sim::GeneratorOptions o;
    o.imageSize = {800, 600};
    const auto f = generate(o);
    EXPECT_EQ(f.image.type(), CV_16UC1);
    EXPECT_EQ(f.image.size(), cv::Size(800, 600));
    o.stain = sim::Stain::Brightfield;
    const auto b = generate(o);
    EXPECT_EQ(b.image.type(), CV_8UC3);
    const auto& t = b.truth;
    EXPECT_EQ(t.atlasX.type(), CV_32FC1);
    EXPECT_EQ(t.atlasY.type(), CV_32FC1);
    EXPECT_EQ(t.labelsInImage.type(), CV_32SC1);
    EXPECT_EQ(t.tissueMask.type(), CV_8UC1);
    EXPECT_EQ(t.damageMask.type(), CV_8UC1);
    for (const cv::Mat* m : {&t.atlasX, &t.atlasY, &t.labelsInImage, &t.tissueMask, &t.damageMask})
        EXPECT_EQ(m->size(), cv::Size(800, 600));
}

TEST(SectionGenerator, FluorescenceIsBrightTissueOnDarkGlassWithoutSaturation) {
    sim::GeneratorOptions o;
    o.seed = 3;
    const auto g = generate(o);
    double minV = 0, maxV = 0;
    cv::minMaxLoc(g.image, &minV, &maxV);
    EXPECT_LT(maxV, 65535);
    EXPECT_GT(maxV, 30000); // most of the 16-bit range is used
    const cv::Mat glass = ~dilated(g.truth.tissueMask, 20);
    const double tissue = medianOf(g.image, eroded(g.truth.tissueMask, 3));
    EXPECT_GT(tissue, 4 * medianOf(g.image, glass));
}

TEST(SectionGenerator, BrightfieldIsPinkPurpleTissueOnBrightGlass) {
    sim::GeneratorOptions o;
    o.seed = 4;
    o.imageSize = kQuickSize;
    o.stain = sim::Stain::Brightfield;
    const auto g = generate(o);
    std::vector<cv::Mat> bgr;
    cv::split(g.image, bgr);
    const cv::Mat tissue = eroded(g.truth.tissueMask, 3);
    const cv::Mat glass = ~dilated(g.truth.tissueMask, 20);
    EXPECT_GT(medianOf(bgr[1], glass), 180);
    EXPECT_LT(medianOf(bgr[1], tissue), medianOf(bgr[1], glass) - 50);
    // Red and blue above green: a pink-purple tint.
    EXPECT_GT(medianOf(bgr[2], tissue), medianOf(bgr[1], tissue) + 20);
    EXPECT_GT(medianOf(bgr[0], tissue), medianOf(bgr[1], tissue) + 20);
}

TEST(SectionGenerator, LandmarksLieInIntactTissueAndCarryTheExactMap) {
    sim::GeneratorOptions o;
    o.seed = 5;
    const auto g = generate(o);
    const auto& t = g.truth;
    ASSERT_EQ(t.landmarks.size(), 200u);
    double minSpacing = 1e9;
    for (size_t i = 0; i < t.landmarks.size(); ++i) {
        const auto& l = t.landmarks[i];
        const int x = static_cast<int>(l.image.x), y = static_cast<int>(l.image.y);
        ASSERT_EQ(l.image.x, x); // landmarks sit on pixel centres
        ASSERT_EQ(l.image.y, y);
        EXPECT_EQ(t.tissueMask.at<std::uint8_t>(y, x), 255);
        EXPECT_EQ(t.damageMask.at<std::uint8_t>(y, x), 0);
        EXPECT_NEAR(t.atlasX.at<float>(y, x), l.atlas.x, 1e-3);
        EXPECT_NEAR(t.atlasY.at<float>(y, x), l.atlas.y, 1e-3);
        const int ax = static_cast<int>(std::lround(l.atlas.x));
        const int ay = static_cast<int>(std::lround(l.atlas.y));
        ASSERT_TRUE(ax >= 0 && ay >= 0 && ax < atlas().cols && ay < atlas().rows);
        EXPECT_GT(atlas().at<std::int32_t>(ay, ax), 0);
        for (size_t j = 0; j < i; ++j)
            minSpacing = std::min(minSpacing, cv::norm(l.image - t.landmarks[j].image));
    }
    // Spread out: much more than a random draw's closest pair would be (a few px).
    EXPECT_GT(minSpacing, 15.0);
}

TEST(SectionGenerator, LabelsInImageAreTheAtlasSeenThroughTheMap) {
    sim::GeneratorOptions o;
    o.seed = 6;
    o.imageSize = kQuickSize;
    const auto g = generate(o);
    const auto& t = g.truth;
    int checked = 0, agree = 0;
    for (int y = 0; y < t.atlasX.rows; y += 7)
        for (int x = 0; x < t.atlasX.cols; x += 7) {
            const int ax = static_cast<int>(std::lround(t.atlasX.at<float>(y, x)));
            const int ay = static_cast<int>(std::lround(t.atlasY.at<float>(y, x)));
            const bool inside = ax >= 0 && ay >= 0 && ax < atlas().cols && ay < atlas().rows;
            const std::int32_t expected = inside ? atlas().at<std::int32_t>(ay, ax) : 0;
            ++checked;
            agree += expected == t.labelsInImage.at<std::int32_t>(y, x);
        }
    // Rounding conventions may differ exactly at half-pixels, nowhere else.
    EXPECT_GT(agree, checked * 999 / 1000);
}

TEST(SectionGenerator, TissueStaysInsideTheImageForAnyRotation) {
    for (std::uint64_t seed = 20; seed < 26; ++seed) {
        sim::GeneratorOptions o;
        o.seed = seed;
        o.imageSize = {700, 500};
        o.maxRotationDeg = 180;
        o.fillFraction = 0.9;
        o.damage.fragment = seed % 2 == 0;
        const auto g = generate(o);
        const cv::Mat any = (g.truth.labelsInImage > 0) | g.truth.tissueMask;
        const cv::Rect box = cv::boundingRect(any);
        EXPECT_GT(box.area(), 0);
        EXPECT_GE(box.x, 2) << "seed " << seed;
        EXPECT_GE(box.y, 2) << "seed " << seed;
        EXPECT_LE(box.br().x, o.imageSize.width - 2) << "seed " << seed;
        EXPECT_LE(box.br().y, o.imageSize.height - 2) << "seed " << seed;
    }
}

TEST(SectionGenerator, TissueFillsAboutTheRequestedFraction) {
    sim::GeneratorOptions o;
    o.seed = 9;
    o.maxRotationDeg = 0;
    o.maxShear = 0;
    o.maxAnisotropy = 0;
    const auto g = generate(o);
    const cv::Rect box = cv::boundingRect(g.truth.labelsInImage > 0);
    EXPECT_NEAR(double(box.width) / o.imageSize.width, o.fillFraction, 0.06);
}

TEST(SectionGenerator, WithoutWarpTheMapIsTheAffine) {
    sim::GeneratorOptions o;
    o.seed = 10;
    o.warpAmplitudeFrac = 0;
    const auto g = generate(o);
    const cv::Matx23d& a = g.truth.affineAtlasFromImage;
    for (int y = 0; y < o.imageSize.height; y += 37)
        for (int x = 0; x < o.imageSize.width; x += 41) {
            EXPECT_NEAR(g.truth.atlasX.at<float>(y, x), a(0, 0) * x + a(0, 1) * y + a(0, 2), 1e-3);
            EXPECT_NEAR(g.truth.atlasY.at<float>(y, x), a(1, 0) * x + a(1, 1) * y + a(1, 2), 1e-3);
        }
}

TEST(SectionGenerator, WarpIsSmallSmoothAndInvertible) {
    sim::GeneratorOptions o;
    o.seed = 11;
    o.warpAmplitudeFrac = 0.03;
    const auto g = generate(o);
    const auto& t = g.truth;
    const cv::Rect atlasBox = cv::boundingRect(atlas() > 0);
    const double limit = o.warpAmplitudeFrac * atlasBox.width;
    double peak = 0, minDet = 1e9, maxDet = 0;
    const cv::Mat tissue = t.labelsInImage > 0;
    for (int y = 1; y < t.atlasX.rows - 1; y += 5)
        for (int x = 1; x < t.atlasX.cols - 1; x += 5) {
            const cv::Matx23d& a = t.affineAtlasFromImage;
            const double dx = t.atlasX.at<float>(y, x) - (a(0, 0) * x + a(0, 1) * y + a(0, 2));
            const double dy = t.atlasY.at<float>(y, x) - (a(1, 0) * x + a(1, 1) * y + a(1, 2));
            if (tissue.at<std::uint8_t>(y, x))
                peak = std::max(peak, std::hypot(dx, dy));
            const double j00 = (t.atlasX.at<float>(y, x + 1) - t.atlasX.at<float>(y, x - 1)) / 2;
            const double j01 = (t.atlasX.at<float>(y + 1, x) - t.atlasX.at<float>(y - 1, x)) / 2;
            const double j10 = (t.atlasY.at<float>(y, x + 1) - t.atlasY.at<float>(y, x - 1)) / 2;
            const double j11 = (t.atlasY.at<float>(y + 1, x) - t.atlasY.at<float>(y - 1, x)) / 2;
            const double det = j00 * j11 - j01 * j10;
            minDet = std::min(minDet, det);
            maxDet = std::max(maxDet, det);
        }
    EXPECT_GT(peak, 0.3 * limit);
    EXPECT_LT(peak, 1.02 * limit);
    const double affineDet =
        cv::determinant(cv::Matx22d(t.affineAtlasFromImage(0, 0), t.affineAtlasFromImage(0, 1),
                                    t.affineAtlasFromImage(1, 0), t.affineAtlasFromImage(1, 1)));
    // Orientation-preserving everywhere and never far from the affine's area change.
    EXPECT_GT(minDet * affineDet, 0);
    EXPECT_GT(minDet / affineDet, 0.4);
    EXPECT_LT(maxDet / affineDet, 1.6);
}

TEST(SectionGenerator, CleanSectionHasNoDamageAndFullTissue) {
    sim::GeneratorOptions o;
    o.seed = 12;
    o.imageSize = kQuickSize;
    const auto g = generate(o);
    EXPECT_TRUE(g.truth.damage.empty());
    EXPECT_EQ(cv::countNonZero(g.truth.damageMask), 0);
    EXPECT_EQ(cv::countNonZero(g.truth.tissueMask != intactTissue(g.truth)), 0);
}

TEST(SectionGenerator, TearIsAThinCrackFromTheBoundaryShowingGlass) {
    for (std::uint64_t seed : {13u, 14u, 15u}) {
        sim::GeneratorOptions o;
        o.seed = seed;
        o.imageSize = kQuickSize;
        o.damage.tear = true;
        const auto g = generate(o);
        const auto& t = g.truth;
        const auto* tear = findDamage(t, sim::DamageKind::Tear);
        ASSERT_NE(tear, nullptr);
        ASSERT_EQ(t.damage.size(), 1u);
        const cv::Mat removed = t.damageMask == 1;
        const double tissueArea = cv::countNonZero(intactTissue(t));
        EXPECT_EQ(tear->areaPx, cv::countNonZero(removed));
        EXPECT_GT(tear->areaPx, 0.001 * tissueArea) << "seed " << seed;
        EXPECT_LT(tear->areaPx, 0.06 * tissueArea) << "seed " << seed;
        EXPECT_GE(tear->polygon.size(), 3u);
        EXPECT_EQ(cv::countNonZero(t.tissueMask & removed), 0);
        // The crack shows glass: as dark as the slide, far darker than tissue.
        EXPECT_LT(medianOf(g.image, eroded(removed, 3)), glassLine(g));
        // Elongated: the crack reaches much further than its width.
        const cv::RotatedRect r = cv::minAreaRect(tear->polygon);
        EXPECT_GT(std::max(r.size.width, r.size.height), 3 * std::min(r.size.width, r.size.height));
        // Outside the damage the outline is untouched.
        EXPECT_EQ(cv::countNonZero((t.tissueMask != intactTissue(t)) & (t.damageMask == 0)), 0);
    }
}

TEST(SectionGenerator, MissingChunkSitsOnTheBoundary) {
    sim::GeneratorOptions o;
    o.seed = 16;
    o.imageSize = kQuickSize;
    o.damage.missing = true;
    const auto g = generate(o);
    const auto& t = g.truth;
    const auto* missing = findDamage(t, sim::DamageKind::Missing);
    ASSERT_NE(missing, nullptr);
    const cv::Mat removed = t.damageMask == 2;
    const double tissueArea = cv::countNonZero(intactTissue(t));
    EXPECT_EQ(missing->areaPx, cv::countNonZero(removed));
    EXPECT_GT(missing->areaPx, 0.003 * tissueArea);
    EXPECT_LT(missing->areaPx, 0.08 * tissueArea);
    // It touches the glass around the section (it is at the boundary).
    EXPECT_GT(cv::countNonZero(dilated(removed, 2) & (t.labelsInImage == 0)), 0);
    EXPECT_LT(medianOf(g.image, eroded(removed, 3)), glassLine(g));
    EXPECT_EQ(cv::countNonZero((t.tissueMask != intactTissue(t)) & (t.damageMask == 0)), 0);
}

TEST(SectionGenerator, FragmentIsCutOffAndMovedClearOfTheSection) {
    for (std::uint64_t seed : {17u, 18u, 19u}) {
        sim::GeneratorOptions o;
        o.seed = seed;
        o.imageSize = kQuickSize;
        o.damage.fragment = true;
        const auto g = generate(o);
        const auto& t = g.truth;
        const auto* fragment = findDamage(t, sim::DamageKind::Fragment);
        ASSERT_NE(fragment, nullptr) << "seed " << seed;
        const cv::Mat tissueBefore = t.labelsInImage > 0;
        const double area = cv::countNonZero(tissueBefore);
        EXPECT_GT(fragment->areaPx, 0.03 * area) << "seed " << seed;
        EXPECT_LT(fragment->areaPx, 0.11 * area) << "seed " << seed;
        // The moved piece is the tissue marked 3 (it may partly cover its old place); the rest
        // of its old place is a glass hole.
        const cv::Mat moved = t.tissueMask & (t.damageMask == 3);
        const cv::Mat main = t.tissueMask & (t.damageMask != 3);
        EXPECT_NEAR(cv::countNonZero(moved), fragment->areaPx, 0.1 * fragment->areaPx)
            << "seed " << seed;
        EXPECT_EQ(cv::countNonZero(dilated(moved, 2) & main), 0) << "seed " << seed;
        const cv::Mat hole = (t.damageMask == 3) & ~t.tissueMask & tissueBefore;
        EXPECT_LT(medianOf(g.image, eroded(hole, 3)), glassLine(g));
        // The motion takes the piece's centre to the moved piece's centre.
        const cv::Moments mp = cv::moments(fragment->polygon);
        const cv::Point2d pc(mp.m10 / mp.m00, mp.m01 / mp.m00);
        const cv::Moments mm = cv::moments(moved, true);
        const cv::Point2d movedCentre(mm.m10 / mm.m00, mm.m01 / mm.m00);
        const cv::Matx23d& m = fragment->motion;
        const cv::Point2d predicted(m(0, 0) * pc.x + m(0, 1) * pc.y + m(0, 2),
                                    m(1, 0) * pc.x + m(1, 1) * pc.y + m(1, 2));
        EXPECT_LT(cv::norm(predicted - movedCentre), 10.0) << "seed " << seed;
    }
}

TEST(SectionGenerator, AllDamageKindsTogetherAndLandmarksAvoidThem) {
    sim::GeneratorOptions o;
    o.seed = 21;
    o.imageSize = kQuickSize;
    o.damage = {true, true, true};
    o.landmarkCount = 300;
    const auto g = generate(o);
    const auto& t = g.truth;
    ASSERT_EQ(t.damage.size(), 3u);
    EXPECT_NE(findDamage(t, sim::DamageKind::Tear), nullptr);
    EXPECT_NE(findDamage(t, sim::DamageKind::Missing), nullptr);
    EXPECT_NE(findDamage(t, sim::DamageKind::Fragment), nullptr);
    EXPECT_EQ(t.landmarks.size(), 300u);
    const cv::Mat damage = dilated(t.damageMask > 0, 3);
    for (const auto& l : t.landmarks) {
        const int x = static_cast<int>(l.image.x), y = static_cast<int>(l.image.y);
        EXPECT_EQ(damage.at<std::uint8_t>(y, x), 0);
        EXPECT_EQ(t.tissueMask.at<std::uint8_t>(y, x), 255);
    }
}

TEST(SectionGenerator, DamageModelsOfIssue18LeaveTheOldCasesUnchanged) {
    sim::GeneratorOptions o;
    o.seed = 22;
    o.imageSize = kQuickSize;
    o.damage.tear = true;
    const auto before = generate(o);
    // The models draw on their own random stream: asking for one keeps the first kinds' damage
    // where it was, and every pixel away from the new crack's blur keeps its value.
    sim::GeneratorOptions withModel = o;
    withModel.damage.crack = true;
    const auto after = generate(withModel);
    ASSERT_EQ(after.truth.damage.size(), 2u);
    EXPECT_EQ(after.truth.damage[0].polygon, before.truth.damage[0].polygon);
    const cv::Mat away = ~dilated(after.truth.damageMask == 1, 10);
    cv::Mat differs;
    cv::compare(before.image, after.image, differs, cv::CMP_NE);
    EXPECT_EQ(cv::countNonZero(differs & away), 0);
    EXPECT_GT(cv::countNonZero(differs), 0);
}

TEST(SectionGenerator, ThinCrackCrossesTheTissueAFewPixelsWide) {
    for (std::uint64_t seed : {23u, 24u, 25u}) {
        sim::GeneratorOptions o;
        o.seed = seed;
        o.damage.crack = true; // 1500 px wide: the crack is 1-5 px
        const auto g = generate(o);
        const auto& t = g.truth;
        ASSERT_EQ(t.damage.size(), 1u) << "seed " << seed;
        EXPECT_EQ(t.damage[0].kind, sim::DamageKind::Tear);
        const cv::Mat crack = t.damageMask == 1;
        // Mean width: area over half the outline's length (a thin shape's length).
        const double halfPerimeter = 0.5 * cv::arcLength(t.damage[0].polygon, true);
        const double meanWidth = cv::countNonZero(crack) / std::max(1.0, halfPerimeter);
        EXPECT_GE(meanWidth, 1.0) << "seed " << seed;
        EXPECT_LE(meanWidth, 5.5) << "seed " << seed;
        const cv::RotatedRect r = cv::minAreaRect(t.damage[0].polygon);
        EXPECT_GT(std::max(r.size.width, r.size.height), 100.0) << "seed " << seed;
        EXPECT_EQ(cv::countNonZero(t.tissueMask & crack), 0);
    }
}

TEST(SectionGenerator, FoldDoublesABandAndMovesTheEdgeIn) {
    int folds = 0;
    for (std::uint64_t seed : {26u, 27u, 28u}) {
        sim::GeneratorOptions o;
        o.seed = seed;
        o.imageSize = kQuickSize;
        o.damage.fold = true;
        const auto g = generate(o);
        o.damage.fold = false;
        const auto clean = generate(o);
        const auto* fold = findDamage(g.truth, sim::DamageKind::Fold);
        if (!fold)
            continue;
        ++folds;
        const cv::Mat marked = g.truth.damageMask == 4;
        const cv::Mat band = eroded(marked & g.truth.tissueMask, 3);
        const cv::Mat place = eroded(marked & ~g.truth.tissueMask & intactTissue(g.truth), 3);
        ASSERT_GT(cv::countNonZero(band), 50) << "seed " << seed;
        ASSERT_GT(cv::countNonZero(place), 50) << "seed " << seed;
        // The band carries two layers: what it gained is the flap's own stain (gain 0.85-1; means,
        // since the fold adds: the flap's mirror image covers the band). Each image is exposed
        // for its brightest tissue, so levels are taken relative to the tissue far from the fold.
        const cv::Mat far = eroded(g.truth.tissueMask, 3) & ~dilated(marked, 40);
        const auto level = [&](const cv::Mat& image, const cv::Mat& where) {
            const double glassLevel = medianOf(image, ~dilated(g.truth.tissueMask, 20));
            return (cv::mean(image, where)[0] - glassLevel) /
                   (cv::mean(image, far)[0] - glassLevel);
        };
        const double gained = level(g.image, band) - level(clean.image, band);
        const double flap = level(clean.image, place);
        EXPECT_GT(gained / flap, 0.6) << "seed " << seed;
        EXPECT_LT(gained / flap, 1.25) << "seed " << seed;
        // The flap's place shows glass.
        EXPECT_LT(medianOf(g.image, place), glassLine(g)) << "seed " << seed;
    }
    EXPECT_GE(folds, 2);
}

TEST(SectionGenerator, SmallFragmentTornVentricleAndChatter) {
    sim::GeneratorOptions o;
    o.seed = 29;
    o.imageSize = kQuickSize;
    o.damage.smallFragment = o.damage.tornVentricle = o.damage.chatter = true;
    const auto g = generate(o);
    const auto& t = g.truth;
    const double area = cv::countNonZero(t.labelsInImage > 0);
    const auto* fragment = findDamage(t, sim::DamageKind::Fragment);
    ASSERT_NE(fragment, nullptr);
    EXPECT_LT(fragment->areaPx, 0.04 * area);
    const auto* torn = findDamage(t, sim::DamageKind::Tear);
    ASSERT_NE(torn, nullptr);
    // The torn wall opens into a ventricle: the wedge touches its glass.
    const cv::Mat ventricle = (t.labelsInImage > 0) & (t.labelsInImage == 73);
    EXPECT_GT(cv::countNonZero(dilated(t.damageMask == 1, 4) & ventricle), 0);
    const auto* chatter = findDamage(t, sim::DamageKind::Chatter);
    ASSERT_NE(chatter, nullptr);
    EXPECT_GT(cv::countNonZero((t.damageMask == 5) & t.tissueMask), 0);
}

TEST(SectionGenerator, EnlargedVentriclesAndAnOpenedFissureAreNotDamage) {
    sim::GeneratorOptions o;
    o.seed = 33;
    o.imageSize = kQuickSize;
    const auto plain = generate(o);
    o.anatomy.ventricleGrowthFrac = 0.015;
    o.anatomy.fissureOpenFrac = 0.01;
    const auto g = generate(o);
    EXPECT_TRUE(g.truth.damage.empty());
    EXPECT_EQ(cv::countNonZero(g.truth.damageMask), 0);
    const cv::Mat lost = plain.truth.tissueMask & ~g.truth.tissueMask;
    EXPECT_GT(cv::countNonZero(lost), 0);
    // The ventricles grew: glass beside the atlas's ventricles.
    const cv::Mat ventricle = g.truth.labelsInImage == 73;
    EXPECT_GT(cv::countNonZero(lost & dilated(ventricle, 3)), 0);
    // Landmarks stay on tissue.
    for (const auto& l : g.truth.landmarks)
        EXPECT_EQ(g.truth.tissueMask.at<std::uint8_t>(cv::Point(l.image)), 255);
    o.anatomy.fissureOpenFrac = 0.5;
    EXPECT_FALSE(sim::generateSection(atlas(), o).ok());
}

TEST(SectionGenerator, DebrisNeverTouchesTheTissue) {
    for (std::uint64_t seed : {30u, 31u, 32u}) {
        sim::GeneratorOptions o;
        o.seed = seed;
        o.imageSize = kQuickSize;
        o.damage.fragment = seed == 31;
        const auto g = generate(o);
        const cv::Mat near = dilated(g.truth.tissueMask, 9) & ~dilated(g.truth.tissueMask, 6);
        const double glass = medianOf(g.image, ~dilated(g.truth.tissueMask, 20));
        const double tissue = medianOf(g.image, eroded(g.truth.tissueMask, 3));
        double maxNear = 0;
        cv::minMaxLoc(g.image, nullptr, &maxNear, nullptr, nullptr, near);
        EXPECT_LT(maxNear, glass + 0.25 * (tissue - glass)) << "seed " << seed;
    }
}

TEST(SectionGenerator, HandlesSparseAllenLikeIds) {
    // A real collapsed Allen plane carries ids like these, with fibre tracts and ventricles.
    cv::Mat labels(160, 228, CV_32S, cv::Scalar(0));
    cv::ellipse(labels, {114, 80}, {95, 65}, 0, 0, 360, cv::Scalar(614454277), cv::FILLED);
    cv::ellipse(labels, {114, 90}, {60, 40}, 0, 0, 360, cv::Scalar(549), cv::FILLED);
    cv::ellipse(labels, {114, 80}, {70, 50}, 0, 180, 360, cv::Scalar(1009), 4);
    cv::ellipse(labels, {90, 80}, {4, 12}, 0, 0, 360, cv::Scalar(73), cv::FILLED);
    sim::GeneratorOptions o;
    o.imageSize = {600, 450};
    o.damage.tear = true;
    const auto g = generate(o, labels);
    ASSERT_FALSE(g.image.empty());
    EXPECT_GT(g.truth.landmarks.size(), 100u);
    EXPECT_GT(cv::countNonZero(g.truth.labelsInImage == 73), 0);
    EXPECT_EQ(cv::countNonZero(g.truth.tissueMask & (g.truth.labelsInImage == 73)), 0);
}

TEST(SectionGenerator, RejectsBadInputWithInvalidArgument) {
    const auto expectInvalid = [](const cv::Mat& labels, const sim::GeneratorOptions& o,
                                  const std::string& what) {
        const auto r = sim::generateSection(labels, o);
        ASSERT_FALSE(r.ok()) << what;
        EXPECT_EQ(r.error().code, core::ErrorCode::InvalidArgument) << what;
        EXPECT_FALSE(r.error().message.empty()) << what;
    };
    const sim::GeneratorOptions good;
    expectInvalid(cv::Mat(), good, "empty labels");
    cv::Mat bytes;
    atlas().convertTo(bytes, CV_8U);
    expectInvalid(bytes, good, "CV_8U labels");
    cv::Mat floats;
    atlas().convertTo(floats, CV_32F);
    expectInvalid(floats, good, "CV_32F labels");
    expectInvalid(cv::Mat(10, 10, CV_32SC2, cv::Scalar(5, 5)), good, "two channels");
    expectInvalid(cv::Mat(50, 50, CV_32S, cv::Scalar(0)), good, "no tissue");
    expectInvalid(cv::Mat(50, 50, CV_32S, cv::Scalar(-3)), good, "only negative labels");

    const std::vector<std::pair<std::string, std::function<void(sim::GeneratorOptions&)>>> bad = {
        {"width 299", [](auto& o) { o.imageSize.width = 299; }},
        {"height 299", [](auto& o) { o.imageSize.height = 299; }},
        {"width 10001", [](auto& o) { o.imageSize.width = 10001; }},
        {"height 10001", [](auto& o) { o.imageSize.height = 10001; }},
        {"fill 0", [](auto& o) { o.fillFraction = 0; }},
        {"fill 1", [](auto& o) { o.fillFraction = 1.0; }},
        {"fill NaN", [](auto& o) { o.fillFraction = std::nan(""); }},
        {"rotation -1", [](auto& o) { o.maxRotationDeg = -1; }},
        {"rotation 181", [](auto& o) { o.maxRotationDeg = 181; }},
        {"anisotropy", [](auto& o) { o.maxAnisotropy = 0.6; }},
        {"shear", [](auto& o) { o.maxShear = -0.1; }},
        {"translation", [](auto& o) { o.maxTranslationFrac = 0.7; }},
        {"warp", [](auto& o) { o.warpAmplitudeFrac = 0.2; }},
        {"warp inf",
         [](auto& o) { o.warpAmplitudeFrac = std::numeric_limits<double>::infinity(); }},
        {"noise", [](auto& o) { o.noise = -1; }},
        {"landmarks", [](auto& o) { o.landmarkCount = -1; }},
        {"stain", [](auto& o) { o.stain = static_cast<sim::Stain>(7); }},
    };
    for (const auto& [what, change] : bad) {
        sim::GeneratorOptions o;
        change(o);
        expectInvalid(atlas(), o, what);
    }
    // The edges of the ranges are accepted.
    sim::GeneratorOptions edge;
    edge.imageSize = {300, 300};
    edge.noise = 0;
    edge.landmarkCount = 0;
    edge.maxRotationDeg = 180;
    const auto r = sim::generateSection(atlas(), edge);
    ASSERT_TRUE(r.ok()) << r.error().message;
    EXPECT_TRUE(r->truth.landmarks.empty());
}

// Not a check: writes images for a human to look at, under <build>/artifacts/simulators.
TEST(SectionGenerator, WritesExampleImagesForInspection) {
    const auto dir = std::filesystem::path(SLST_BINARY_DIR) / "artifacts" / "simulators";
    std::filesystem::create_directories(dir);
    const auto save = [&](const std::string& name, const cv::Mat& image) {
        cv::Mat view = image;
        if (image.depth() == CV_16U) {
            // 16-bit PNGs look black in most viewers: also write a stretched 8-bit copy.
            double maxV = 0;
            cv::minMaxLoc(image, nullptr, &maxV);
            image.convertTo(view, CV_8U, 255.0 / std::max(1.0, maxV));
        }
        EXPECT_TRUE(cv::imwrite((dir / (name + ".png")).string(), view)) << name;
    };
    struct Case {
        std::string name;
        sim::Stain stain;
        sim::DamageOptions damage;
        double ap;
    };
    const std::vector<Case> cases = {
        {"fluorescence", sim::Stain::Fluorescence, {}, 0.5},
        {"brightfield", sim::Stain::Brightfield, {}, 0.35},
        {"tear", sim::Stain::Fluorescence, {true, false, false}, 0.6},
        {"missing", sim::Stain::Fluorescence, {false, true, false}, 0.45},
        {"fragment", sim::Stain::Fluorescence, {false, false, true}, 0.55},
        {"all-damage-brightfield", sim::Stain::Brightfield, {true, true, true}, 0.5},
    };
    std::uint64_t seed = 100;
    for (const Case& c : cases) {
        sim::GeneratorOptions o;
        o.seed = seed++;
        o.stain = c.stain;
        o.damage = c.damage;
        const auto g = generate(o, sim::builtinAtlasPlane(c.ap));
        save(c.name, g.image);
        save(c.name + "-damage-mask", g.truth.damageMask * 80);
    }
    // The atlas series, coloured with the Allen colours.
    std::map<std::int32_t, cv::Vec3b> colours;
    for (const auto& r : sim::builtinRegions())
        colours[r.id] = {static_cast<std::uint8_t>(r.colorRgb & 0xFF),
                         static_cast<std::uint8_t>((r.colorRgb >> 8) & 0xFF),
                         static_cast<std::uint8_t>((r.colorRgb >> 16) & 0xFF)};
    std::vector<cv::Mat> tiles;
    for (int i = 0; i < 6; ++i) {
        const cv::Mat plane = sim::builtinAtlasPlane(i / 5.0);
        cv::Mat tile(plane.size(), CV_8UC3, cv::Scalar::all(0));
        for (int r = 0; r < plane.rows; ++r)
            for (int c = 0; c < plane.cols; ++c)
                if (const auto id = plane.at<std::int32_t>(r, c); id > 0)
                    tile.at<cv::Vec3b>(r, c) = colours[id];
        tiles.push_back(tile);
    }
    cv::Mat top, bottom, all;
    cv::hconcat(std::vector<cv::Mat>(tiles.begin(), tiles.begin() + 3), top);
    cv::hconcat(std::vector<cv::Mat>(tiles.begin() + 3, tiles.end()), bottom);
    cv::vconcat(top, bottom, all);
    save("builtin-atlas-series", all);
}
