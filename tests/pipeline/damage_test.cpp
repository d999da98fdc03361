#include "slicestation/pipeline/damage.hpp"
#include "slicestation/pipeline/mask_ops.hpp"
#include "slicestation/pipeline/medial_axis.hpp"

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

#include <cmath>

using namespace slicestation::pipeline;

namespace {
/// A square with a narrow wedge cut into its left side, `depth` px deep, sides every 2 px.
std::vector<cv::Point2f> notchedSquare(float depth, double step = 2.0) {
    return subdivide({{0, 0}, {200, 0}, {200, 200}, {0, 200}, {0, 108}, {depth, 100}, {0, 92}},
                     step);
}

cv::Mat ellipseMask(cv::Size size, cv::Point c, cv::Size axes) {
    cv::Mat m = cv::Mat::zeros(size, CV_8U);
    cv::ellipse(m, c, axes, 0, 0, 360, cv::Scalar(255), cv::FILLED);
    return m;
}
} // namespace

TEST(MedialAxis, MarksInsideAndOutsideFaces) {
    const ExteriorTriangulation convex = exteriorMedialAxis({{0, 0}, {100, 0}, {100, 80}, {0, 80}});
    EXPECT_EQ(convex.insideFaces, 2);
    EXPECT_EQ(convex.exteriorFaces, 0); // a convex outline has nothing outside within its hull
    const ExteriorTriangulation notched = exteriorMedialAxis(notchedSquare(80));
    EXPECT_GT(notched.exteriorFaces, 0);
    EXPECT_GT(notched.insideFaces, 0);
}

TEST(MedialAxis, BranchLengthFollowsTheNotchDepth) {
    double shallow = 0, deep = 0;
    for (const auto& b : exteriorMedialAxis(notchedSquare(20)).branches)
        shallow = std::max(shallow, b.length);
    for (const auto& b : exteriorMedialAxis(notchedSquare(120)).branches)
        deep = std::max(deep, b.length);
    EXPECT_GT(deep, 60.0); // the axis runs most of the way down a 120 px wedge
    EXPECT_GT(deep, 3 * shallow);
}

TEST(MedialAxis, AlphaIsALengthNotAHopCount) {
    // The same notch sampled five times more densely has many more Voronoi vertices but about
    // the same depth.
    double sparse = 0, fine = 0;
    size_t sparseNodes = 0, fineNodes = 0;
    for (const auto& b : exteriorMedialAxis(notchedSquare(120, 2.5)).branches)
        if (b.length > sparse) {
            sparse = b.length;
            sparseNodes = b.axis.size();
        }
    for (const auto& b : exteriorMedialAxis(notchedSquare(120, 0.5)).branches)
        if (b.length > fine) {
            fine = b.length;
            fineNodes = b.axis.size();
        }
    EXPECT_GT(fineNodes, 2 * sparseNodes);
    EXPECT_NEAR(fine, sparse, 0.2 * sparse);
}

TEST(Damage, SymmetricNotchesAreAnatomyAndALoneOneIsNot) {
    // An ellipse with notches at both sides (anatomy) and one more on the lower left only.
    cv::Mat mask = ellipseMask({600, 400}, {300, 200}, {250, 160});
    const auto cut = [&](std::vector<cv::Point> tri) {
        cv::fillPoly(mask, std::vector<std::vector<cv::Point>>{tri}, cv::Scalar(0));
    };
    cut({{40, 150}, {150, 160}, {40, 170}});   // left
    cut({{560, 150}, {450, 160}, {560, 170}}); // its mirror
    cut({{80, 285}, {200, 240}, {100, 325}});  // lone tear, open to the outside
    const Outline outline = tissueOutline(mask);
    auto concavities = deepConcavities(outline, 40.0);
    ASSERT_GE(concavities.size(), 3u);
    const cv::Matx23d mirror(-1, 0, 600 - 1, 0, 1, 0); // about x = 299.5
    markSymmetric(concavities, outline, mirror, 500, DamageParams{});
    int symmetric = 0, lone = 0;
    for (const auto& c : concavities) {
        cv::Point2f centre(0, 0);
        for (const auto& p : c.points)
            centre += p;
        centre *= 1.0f / float(c.points.size());
        if (centre.y > 230 && centre.x < 250) {
            EXPECT_FALSE(c.symmetric);
            ++lone;
        } else if (std::abs(centre.y - 160) < 40) {
            EXPECT_TRUE(c.symmetric) << "at " << centre;
            ++symmetric;
        }
    }
    EXPECT_EQ(lone, 1);
    EXPECT_EQ(symmetric, 2);
    const cv::Mat excluded = concavityExclusion(concavities, mask.size(), 5);
    EXPECT_GT(excluded.at<uchar>(265, 150), 0); // around the lone tear
    EXPECT_EQ(excluded.at<uchar>(160, 100), 0); // not around the symmetric ones
}

TEST(Damage, GapsTearsAndFragmentsAgainstTheExpectedTissue) {
    const cv::Mat expected = ellipseMask({600, 400}, {300, 200}, {250, 160});
    cv::Mat tissue = expected.clone();
    cv::circle(tissue, {300, 120}, 30, cv::Scalar(0), cv::FILLED); // missing chunk
    cv::line(tissue, {420, 200}, {520, 260}, cv::Scalar(0), 4);    // thin crack
    cv::ellipse(tissue, {60, 60}, {25, 15}, 0, 0, 360, cv::Scalar(255), cv::FILLED); // fragment
    const auto regions = tissueDamage(tissue, {expected, expected, {}}, 500, DamageParams{});
    int missing = 0, tears = 0, fragments = 0;
    for (const auto& r : regions) {
        missing += r.kind == DamageKind::Missing;
        tears += r.kind == DamageKind::Tear;
        fragments += r.kind == DamageKind::Fragment;
        EXPECT_GT(r.share, 0.0);
        EXPECT_GE(r.polygon.size(), 3u);
    }
    EXPECT_EQ(missing, 1);
    EXPECT_EQ(tears, 1);
    EXPECT_EQ(fragments, 1);
    EXPECT_TRUE(isDamaged(regions, 500, DamageParams{}));
    EXPECT_NE(damageSummary(regions).find("tear"), std::string::npos);
}

TEST(Damage, ACracksTaperingEndCountsToItsLength) {
    const cv::Mat expected = ellipseMask({600, 400}, {300, 200}, {250, 160});
    // A crack inside the tissue: a wedge 10 px wide narrowing over 40 px, then a thread one
    // pixel wide for 30 px more, which the gap mask's opening removes.
    cv::Mat tissue = expected.clone();
    const std::vector<cv::Point> wedge{{295, 250}, {305, 250}, {300, 210}};
    cv::fillPoly(tissue, std::vector<std::vector<cv::Point>>{wedge}, cv::Scalar(0));
    cv::line(tissue, {300, 210}, {300, 180}, cv::Scalar(0), 1);
    // A stray thread elsewhere is not part of it.
    cv::line(tissue, {100, 150}, {100, 100}, cv::Scalar(0), 1);

    cv::Mat opened;
    const cv::Mat raw = expected & ~tissue;
    cv::morphologyEx(raw, opened, cv::MORPH_OPEN,
                     cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(3, 3)));
    const GapThreads threads = gapThreads(raw, opened);
    cv::Mat region;
    cv::connectedComponents(opened, region);
    region = region == 1;
    std::vector<cv::Point> pts;
    cv::findNonZero(region, pts);
    const cv::RotatedRect box = cv::minAreaRect(pts);
    EXPECT_LT(std::max(box.size.width, box.size.height), 45); // the wedge alone
    EXPECT_NEAR(crackLength(region, threads), 70, 4);         // with its thread

    // 70 px is over the deep-tear length (10% of a 500 px brain); the wedge alone is not, and
    // its area is far under the share rule.
    const auto regions = tissueDamage(tissue, {expected, expected, {}}, 500, DamageParams{});
    ASSERT_EQ(regions.size(), 1u);
    EXPECT_EQ(regions[0].kind, DamageKind::Tear);
    EXPECT_NEAR(regions[0].lengthPx, 70, 4);
    EXPECT_TRUE(isDamaged(regions, 500, DamageParams{}));
}

TEST(Damage, DarkValleysAreThinDarkLinesNotDimTissue) {
    // Textured tissue (0.35-0.65) on glass (0.02), a crack 2 px wide at the glass level, and a
    // patch of evenly dim tissue (0.15, under the darkness limit on its own).
    cv::Mat grey(240, 320, CV_32F, cv::Scalar(0.02f));
    const cv::Mat tissue = ellipseMask(grey.size(), {160, 120}, {140, 100});
    cv::Mat texture(grey.size(), CV_32F);
    cv::RNG rng(7);
    rng.fill(texture, cv::RNG::UNIFORM, 0.35, 0.65);
    texture.copyTo(grey, tissue);
    cv::line(grey, {80, 90}, {200, 110}, cv::Scalar(0.02), 2);
    cv::Mat dim(grey.size(), CV_32F);
    rng.fill(dim, cv::RNG::UNIFORM, 0.13, 0.17);
    const cv::Rect patch(150, 150, 60, 40);
    dim(patch).copyTo(grey(patch));

    const GreyLevels levels = greyLevels(grey, tissue);
    EXPECT_NEAR(levels.glass, 0.02, 1e-4);
    EXPECT_NEAR(levels.tissue, 0.5, 0.02);
    const cv::Mat valleys = darkValleys(grey, levels, DamageParams{});
    cv::Mat line = cv::Mat::zeros(grey.size(), CV_8U);
    cv::line(line, {84, 91}, {196, 109}, cv::Scalar(255), 1);
    EXPECT_GT(cv::countNonZero(valleys & line), 0.9 * cv::countNonZero(line));
    EXPECT_LT(cv::countNonZero(valleys(patch)), 0.02 * patch.area());
    cv::Mat elsewhere = tissue.clone();
    elsewhere(patch).setTo(0);
    cv::line(elsewhere, {80, 90}, {200, 110}, cv::Scalar(0), 8);
    EXPECT_LT(cv::countNonZero(valleys & elsewhere), 0.002 * cv::countNonZero(elsewhere));
}

TEST(Damage, ADeepTearMustBeACrackNotAHole) {
    // The deep-tear rule is for cracks, long and thin; a hole as long but thick (a ventricle
    // wall pulled open) counts by its share only.
    DamageRegion crack;
    crack.kind = DamageKind::Tear;
    crack.share = 0.005;
    crack.lengthPx = 60;
    crack.thicknessPx = 10;
    EXPECT_TRUE(isDamaged({crack}, 500, DamageParams{}));
    DamageRegion hole = crack;
    hole.thicknessPx = 24; // only 2.5 times longer than thick, under crackElongation 3
    EXPECT_FALSE(isDamaged({hole}, 500, DamageParams{}));
    hole.share = 0.009;
    EXPECT_TRUE(isDamaged({hole}, 500, DamageParams{}));
}

TEST(Damage, IntactTissueAndRegistrationSlackAreNotDamage) {
    const cv::Mat expected = ellipseMask({600, 400}, {300, 200}, {250, 160});
    // The section a few pixels smaller all round: slack along the outline, nothing lost.
    const cv::Mat tissue = ellipseMask({600, 400}, {301, 201}, {247, 157});
    const auto regions = tissueDamage(tissue, {expected, expected, {}}, 500, DamageParams{});
    EXPECT_TRUE(regions.empty());
    EXPECT_FALSE(isDamaged(regions, 500, DamageParams{}));
    EXPECT_EQ(damageSummary(regions), "no damage found");
}

TEST(Damage, ALongBandAlongTheOutlineIsAMisfitAndABiteIsNot) {
    const cv::Mat expected = ellipseMask({600, 400}, {300, 200}, {250, 160});
    // The section's top lies 30 px below the atlas outline over most of its width: a crescent
    // about 400 px long, too thick to be slack (shallowFrac 0.05 x 500 = 25 px).
    cv::Mat tissue = ellipseMask({600, 400}, {300, 215}, {250, 145});
    DamageParams p;
    EXPECT_TRUE(tissueDamage(tissue, {expected, expected, {}}, 500, p).empty());
    // A bite out of the bottom, about as deep as wide, is lost tissue.
    cv::circle(tissue, {300, 360}, 45, cv::Scalar(0), cv::FILLED);
    const auto regions = tissueDamage(tissue, {expected, expected, {}}, 500, p);
    ASSERT_EQ(regions.size(), 1u);
    EXPECT_EQ(regions[0].kind, DamageKind::Missing);
    EXPECT_GT(regions[0].polygon.front().y, 300.0f);
    // Without the rule the crescent is reported too: the test above is the rule's doing.
    p.bandElongation = 1e9;
    EXPECT_EQ(tissueDamage(tissue, {expected, expected, {}}, 500, p).size(), 2u);
}

TEST(Damage, PartMapNumbersTheGroupsOfIds) {
    cv::Mat labels(4, 4, CV_32S, cv::Scalar(10));
    labels.at<int>(0, 1) = 11;
    labels.at<int>(1, 0) = 20;
    labels.at<int>(2, 2) = 30;
    labels.at<int>(3, 3) = 0;
    const cv::Mat parts = partMap(labels, {{10, 11}, {20}});
    EXPECT_EQ(parts.at<uchar>(0, 0), 1);
    EXPECT_EQ(parts.at<uchar>(0, 1), 1);
    EXPECT_EQ(parts.at<uchar>(1, 0), 2);
    EXPECT_EQ(parts.at<uchar>(2, 2), 0); // in no group
    EXPECT_EQ(parts.at<uchar>(3, 3), 0); // outside the brain
}

TEST(Damage, AGapAlongAFissureIsNotDamageAndATearThroughAPartIs) {
    const cv::Mat expected = ellipseMask({600, 400}, {300, 200}, {250, 160});
    // Part 1 left of x = 300, part 2 right of it (the atlas as mapped into the section).
    cv::Mat parts = cv::Mat::zeros(expected.size(), CV_8U);
    parts(cv::Rect(0, 0, 300, 400)).setTo(1);
    parts(cv::Rect(300, 0, 300, 400)).setTo(2);
    parts.setTo(0, ~expected);
    DamageParams p;
    cv::Mat along = expected.clone();
    cv::line(along, {304, 90}, {296, 300}, cv::Scalar(0), 12); // the fissure opened
    cv::Mat gap = expected & ~along;
    EXPECT_TRUE(betweenParts(gap, parts, 15, p.fissurePurity));
    EXPECT_TRUE(tissueDamage(along, {expected, expected, parts}, 500, p).empty());
    EXPECT_FALSE(tissueDamage(along, {expected, expected, {}}, 500, p).empty());

    cv::Mat across = expected.clone();
    cv::line(across, {180, 220}, {420, 180}, cv::Scalar(0), 12); // a tear across the interface
    gap = expected & ~across;
    EXPECT_FALSE(betweenParts(gap, parts, 15, p.fissurePurity));
    auto regions = tissueDamage(across, {expected, expected, parts}, 500, p);
    ASSERT_EQ(regions.size(), 1u);
    EXPECT_EQ(regions[0].kind, DamageKind::Tear);
    EXPECT_TRUE(isDamaged(regions, 500, p));

    // A bite out of the edge where the two parts meet: glass on one side, lost tissue.
    cv::Mat bite = expected.clone();
    cv::circle(bite, {300, 40}, 45, cv::Scalar(0), cv::FILLED);
    gap = expected & ~bite;
    cv::Mat tissueParts = cv::Mat::zeros(parts.size(), CV_8U);
    parts.copyTo(tissueParts, bite);
    EXPECT_FALSE(betweenParts(gap, tissueParts, 15, p.fissurePurity));
    regions = tissueDamage(bite, {expected, expected, parts}, 500, p);
    ASSERT_EQ(regions.size(), 1u);
    EXPECT_EQ(regions[0].kind, DamageKind::Missing);

    cv::Mat inside = expected.clone();
    cv::line(inside, {150, 120}, {160, 300}, cv::Scalar(0), 12); // a tear within part 1
    gap = expected & ~inside;
    EXPECT_FALSE(betweenParts(gap, parts, 15, p.fissurePurity));
    regions = tissueDamage(inside, {expected, expected, parts}, 500, p);
    ASSERT_EQ(regions.size(), 1u);
    EXPECT_TRUE(isDamaged(regions, 500, p));
}

TEST(Damage, PiecesInsideKeepsWholePiecesMostlyInTheRegion) {
    cv::Mat pieces = cv::Mat::zeros(200, 300, CV_8U);
    cv::circle(pieces, {60, 100}, 20, cv::Scalar(255), cv::FILLED);  // all inside
    cv::circle(pieces, {150, 100}, 20, cv::Scalar(255), cv::FILLED); // half inside
    cv::circle(pieces, {250, 100}, 20, cv::Scalar(255), cv::FILLED); // outside
    cv::Mat region = cv::Mat::zeros(pieces.size(), CV_8U);
    region(cv::Rect(0, 0, 150, 200)).setTo(255);
    const cv::Mat most = piecesInside(pieces, region, 0.7);
    EXPECT_GT(most.at<uchar>(100, 60), 0);
    EXPECT_EQ(most.at<uchar>(100, 140), 0); // the half-inside piece is left out whole
    EXPECT_EQ(most.at<uchar>(100, 160), 0);
    EXPECT_EQ(most.at<uchar>(100, 250), 0);
    const cv::Mat half = piecesInside(pieces, region, 0.4);
    EXPECT_GT(half.at<uchar>(100, 160), 0); // kept whole, also outside the region
    EXPECT_EQ(half.at<uchar>(100, 250), 0);
    EXPECT_EQ(cv::countNonZero(piecesInside(cv::Mat::zeros(pieces.size(), CV_8U), region, 0.5)), 0);
}

TEST(Damage, ExtraPiecesAreThoseTheAtlasDoesNotHave) {
    cv::Mat tissue = ellipseMask({400, 300}, {200, 150}, {120, 80});
    cv::circle(tissue, {370, 40}, 15, cv::Scalar(255), cv::FILLED);
    const cv::Mat atlasOne = ellipseMask({400, 300}, {200, 150}, {120, 80});
    const cv::Mat extra = extraPieces(tissue, atlasOne);
    ASSERT_FALSE(extra.empty());
    EXPECT_GT(extra.at<uchar>(40, 370), 0);
    EXPECT_EQ(extra.at<uchar>(150, 200), 0);
    // Two bulbs in the atlas and in the section: no fragment.
    cv::Mat two = cv::Mat::zeros(300, 400, CV_8U);
    cv::circle(two, {120, 150}, 60, cv::Scalar(255), cv::FILLED);
    cv::circle(two, {280, 150}, 60, cv::Scalar(255), cv::FILLED);
    EXPECT_TRUE(extraPieces(two, two).empty());
}

TEST(Damage, TheScoreIsOneHalfAtTheDecisionLineAndGrowsWithTheEvidence) {
    const DamageParams p;
    DamageRegion small;
    small.kind = DamageKind::Missing;
    small.share = p.damagedShare / 2;
    DamageRegion other = small;
    std::vector<DamageRegion> one{small};
    const double half = damageScore(one, 500, p);
    EXPECT_GT(half, 0.2);
    EXPECT_LT(half, 0.5);
    EXPECT_FALSE(isDamaged(one, 500, p));
    // Two regions of half the share each reach the line together.
    std::vector<DamageRegion> two{small, other};
    EXPECT_DOUBLE_EQ(damageScore(two, 500, p), 0.5);
    EXPECT_TRUE(isDamaged(two, 500, p));
    EXPECT_NEAR(two[0].score, half, 1e-12); // each region keeps its own score
    // A crack: its length over the deep-tear length, when it is a crack and not a hole.
    DamageRegion crack;
    crack.kind = DamageKind::Tear;
    crack.lengthPx = 2 * p.deepTearFrac * 500;
    crack.thicknessPx = 5;
    std::vector<DamageRegion> c{crack};
    EXPECT_DOUBLE_EQ(damageScore(c, 500, p), 0.75);
    crack.thicknessPx = crack.lengthPx; // as thick as long: a hole, judged by its share only
    std::vector<DamageRegion> h{crack};
    EXPECT_DOUBLE_EQ(damageScore(h, 500, p), 0.0);
    // The threshold is a setting.
    DamageParams strict = p;
    strict.flagScore = 0.8;
    EXPECT_FALSE(isDamaged(c, 500, strict));
    EXPECT_EQ(toString(DamageVerdict::CheckRegistration), "check_registration");
}

namespace {
/// A fluorescence-like section: glass 0.05 with noise, tissue `level` with noise, in `tissue`.
cv::Mat noisySection(const cv::Mat& tissue, float level, float noise, std::uint64_t seed) {
    cv::Mat grey(tissue.size(), CV_32F, cv::Scalar(0.05));
    grey.setTo(level, tissue);
    cv::Mat n(tissue.size(), CV_32F);
    cv::RNG rng(seed);
    rng.fill(n, cv::RNG::NORMAL, 0, noise);
    return grey + n;
}
} // namespace

TEST(Damage, AGapAtADimTissueLevelIsNotGlassAndNotDamage) {
    // A pale tract that the tissue mask left out: its level is far above the glass noise.
    const cv::Mat expected = ellipseMask({600, 400}, {300, 200}, {250, 160});
    cv::Mat tissue = expected.clone();
    cv::ellipse(tissue, {300, 200}, {80, 12}, 20, 0, 360, cv::Scalar(0), cv::FILLED);
    cv::Mat tract = expected & ~tissue;
    cv::Mat grey = noisySection(expected, 0.6f, 0.01f, 3);
    grey.setTo(0.12f, tract); // dim tissue: 7 noise units above the glass
    const auto pale = tissueDamage(tissue, {expected, expected, {}}, 500, DamageParams{}, {}, grey);
    EXPECT_TRUE(pale.empty());
    // The same gap showing glass is damage, with its level near the glass.
    grey.setTo(0.05f, tract);
    const auto torn = tissueDamage(tissue, {expected, expected, {}}, 500, DamageParams{}, {}, grey);
    ASSERT_EQ(torn.size(), 1u);
    EXPECT_LT(std::abs(torn[0].levelNoiseUnits), 3.0);
    EXPECT_LT(torn[0].levelShare, 0.05);
}

TEST(Damage, ThinCracksAreGlassLinesWithTissueBesideThemAwayFromTheMidline) {
    const cv::Mat brain = ellipseMask({1200, 800}, {600, 400}, {500, 320});
    const cv::Mat none = cv::Mat::zeros(brain.size(), CV_8U);
    const AtlasExpectation expected{brain, brain, cv::Mat()};
    const Midline midline{{600, 0}, {600, 800}};
    const DamageParams p;
    // A 3 px crack from the edge, 200 px long (20% of the width): glass showing through.
    cv::Mat tissue = brain.clone();
    cv::line(tissue, {150, 300}, {330, 390}, cv::Scalar(0), 3);
    cv::Mat grey = noisySection(tissue, 0.6f, 0.01f, 5);
    auto cracks = thinCracks(grey, tissue, expected, none, 1000, p, midline);
    ASSERT_EQ(cracks.size(), 1u);
    EXPECT_EQ(cracks[0].kind, DamageKind::Tear);
    EXPECT_NEAR(cracks[0].lengthPx, 200, 25);
    EXPECT_LE(cracks[0].thicknessPx, 5);
    std::vector<DamageRegion> flagged = cracks;
    EXPECT_GE(damageScore(flagged, 1000, p), p.flagScore);
    // Already known as a gap: not reported twice.
    cv::Mat known = brain & ~tissue;
    EXPECT_TRUE(thinCracks(grey, tissue, expected, none, 1000, p, midline, known).empty());
    // The same glass line along the midline is the longitudinal fissure.
    tissue = brain.clone();
    cv::line(tissue, {600, 150}, {602, 400}, cv::Scalar(0), 3);
    grey = noisySection(tissue, 0.6f, 0.01f, 6);
    EXPECT_TRUE(thinCracks(grey, tissue, expected, none, 1000, p, midline).empty());
    // Beside a mapped ventricle, a slit of glass is that ventricle.
    cv::Mat ventricles = none.clone();
    cv::line(ventricles, {400, 500}, {450, 560}, cv::Scalar(255), 4);
    tissue = brain.clone();
    cv::line(tissue, {400, 500}, {450, 560}, cv::Scalar(0), 3);
    grey = noisySection(tissue, 0.6f, 0.01f, 7);
    EXPECT_TRUE(thinCracks(grey, tissue, expected, ventricles, 1000, p, midline).empty());
    // A glass line in dim tissue whose grains go down to the glass level (a fifth of the pixels
    // around it): a web between grains, no crack, since glass lies beside it too.
    tissue = brain.clone();
    cv::line(tissue, {150, 300}, {330, 390}, cv::Scalar(0), 3);
    grey = noisySection(tissue, 0.6f, 0.01f, 8);
    cv::Mat coarse(brain.rows / 3, brain.cols / 3, CV_32F), salt; // grains 3 px across
    cv::RNG rng(9);
    rng.fill(coarse, cv::RNG::UNIFORM, 0.0, 1.0);
    cv::resize(coarse, salt, brain.size(), 0, 0, cv::INTER_NEAREST);
    cv::Mat band = cv::Mat::zeros(brain.size(), CV_8U);
    cv::line(band, {150, 300}, {330, 390}, cv::Scalar(255), 30);
    grey.setTo(0.05f, band & (salt < 0.2f));
    EXPECT_TRUE(thinCracks(grey, tissue, expected, none, 1000, p, midline).empty());
    DamageParams anyWall = p; // the line is there: only the tissue beside tells them apart
    anyWall.crackWallGlass = 1.0;
    EXPECT_FALSE(thinCracks(grey, tissue, expected, none, 1000, anyWall, midline).empty());
}

TEST(Damage, ACrackIsFollowedAcrossAShallowBreakButNotAcrossTissue) {
    const cv::Mat brain = ellipseMask({1200, 800}, {600, 400}, {500, 320});
    const cv::Mat none = cv::Mat::zeros(brain.size(), CV_8U);
    const AtlasExpectation expected{brain, brain, cv::Mat()};
    const Midline midline{{600, 0}, {600, 800}};
    const DamageParams p;
    // A crack of 80 px (8% of the width: a tear, not flagged alone), then a break of `gap` px
    // (where it narrowed to a shallow line, neither glass nor a thread, when `shallow`), then
    // 35 px of it again: a piece (under crackMinFrac, 50 px).
    struct Found {
        std::vector<DamageRegion> regions, pieces, joined;
        double score = 0;
    };
    const auto run = [&](int gap, bool shallow, const DamageParams& params) {
        cv::Mat tissue = brain.clone();
        cv::line(tissue, {200, 300}, {280, 300}, cv::Scalar(0), 3);
        cv::line(tissue, {282 + gap, 300}, {317 + gap, 300}, cv::Scalar(0), 3);
        cv::Mat grey = noisySection(tissue, 0.6f, 0.01f, 11);
        if (shallow) // 0.2 below the tissue (a thread's depth is 0.25 of 0.55)
            cv::line(grey, {282, 300}, {280 + gap, 300}, cv::Scalar(0.4), 1);
        Found f;
        f.regions =
            thinCracks(grey, tissue, expected, none, 1000, params, midline, cv::Mat(), &f.pieces);
        f.joined = continueTears(f.regions, f.pieces, grey, tissue, 1000, params);
        f.score = damageScore(f.regions, 1000, params);
        return f;
    };
    Found f = run(12, true, p);
    ASSERT_EQ(f.regions.size(), 1u);
    ASSERT_EQ(f.pieces.size(), 1u);
    EXPECT_NEAR(f.pieces[0].lengthPx, 37, 4);
    ASSERT_EQ(f.joined.size(), 1u);
    EXPECT_NEAR(f.regions[0].lengthPx, 82 + 37, 8) << "the tear's length runs on along the piece";
    EXPECT_GE(f.score, p.flagScore);
    // Ordinary tissue in the break: two lines, the piece is left out and the tear not flagged.
    f = run(12, false, p);
    ASSERT_EQ(f.regions.size(), 1u);
    EXPECT_EQ(f.pieces.size(), 1u);
    EXPECT_TRUE(f.joined.empty());
    EXPECT_NEAR(f.regions[0].lengthPx, 82, 6);
    EXPECT_LT(f.score, p.flagScore);
    // A break longer than the shortest crack (crackMinFrac, 50 px) is not bridged, shallow or
    // not.
    f = run(60, true, p);
    EXPECT_EQ(f.pieces.size(), 1u);
    EXPECT_TRUE(f.joined.empty());
    EXPECT_LT(f.score, p.flagScore);
    // Switched off: no piece is collected.
    DamageParams off = p;
    off.crackPieceFrac = 0;
    f = run(12, true, off);
    EXPECT_TRUE(f.pieces.empty());
    EXPECT_LT(f.score, p.flagScore);
}

TEST(Damage, ABlurredCrackIsFoundByDefaultButNotInsideADarkAtlasRegion) {
    // A 4 px crack blurred by the optics (1.25 px): its middle keeps about a tenth of the
    // tissue level, far above the glass noise, so only the dark-valley search finds it.
    const cv::Mat brain = ellipseMask({1200, 800}, {600, 400}, {500, 320});
    const cv::Mat none = cv::Mat::zeros(brain.size(), CV_8U);
    const Midline midline{{600, 0}, {600, 800}};
    cv::Mat sharp = cv::Mat::zeros(brain.size(), CV_32F);
    sharp.setTo(0.55f, brain);
    cv::line(sharp, {200, 300}, {420, 420}, cv::Scalar(0), 4);
    cv::Mat grey;
    cv::GaussianBlur(sharp, grey, cv::Size(), 1.25);
    cv::Mat noise(brain.size(), CV_32F);
    cv::RNG rng(21);
    rng.fill(noise, cv::RNG::NORMAL, 0, 0.01);
    grey += noise + cv::Scalar(0.05);
    const cv::Mat tissue = brain.clone(); // the working-size mask does not open the crack
    const AtlasExpectation expected{brain, brain, cv::Mat()};
    const DamageParams p;
    ASSERT_GT(p.crackDarkness, 0) << "the dark-valley search is on by default";
    const auto cracks = thinCracks(grey, tissue, expected, none, 1000, p, midline);
    ASSERT_EQ(cracks.size(), 1u);
    EXPECT_NEAR(cracks[0].lengthPx, 250, 40);
    std::vector<DamageRegion> flagged = cracks;
    EXPECT_GE(damageScore(flagged, 1000, p), p.flagScore);
    DamageParams glassOnly = p;
    glassOnly.crackDarkness = 0;
    EXPECT_TRUE(thinCracks(grey, tissue, expected, none, 1000, glassOnly, midline).empty());
    // The same dark line inside a mapped region the section shows dark (an unstained tract,
    // as in the built-in atlas's callosal band) is that region.
    cv::Mat labels(brain.size(), CV_32S, cv::Scalar(0));
    labels.setTo(1, brain);
    cv::Mat tract = none.clone();
    cv::line(tract, {200, 300}, {420, 420}, cv::Scalar(255), 4);
    labels.setTo(2, tract);
    const GreyLevels levels = greyLevels(grey, tissue & ~tract);
    const cv::Mat dark = darkAtlasRegions(grey, labels, brain, levels, p.crackDarkness);
    EXPECT_EQ(cv::countNonZero(dark & ~tract), 0) << "the bright region is not dark";
    EXPECT_EQ(cv::countNonZero(dark), cv::countNonZero(tract));
    const AtlasExpectation withTract{brain, brain, cv::Mat(), dark};
    EXPECT_TRUE(thinCracks(grey, tissue, withTract, none, 1000, p, midline).empty());
}

TEST(Damage, ACrackCrossingADimRegionIsAValleyInItButATractsThinEndIsNot) {
    // Bright tissue (0.55) with a dim band (0.15: a region stained weakly, wide and long), a
    // 4 px crack of glass crossing tissue and band, everything blurred by the optics.
    const cv::Mat brain = ellipseMask({1200, 800}, {600, 400}, {500, 320});
    const cv::Mat none = cv::Mat::zeros(brain.size(), CV_8U);
    const Midline midline{{600, 0}, {600, 800}};
    const auto render = [&](const cv::Mat& sharp, std::uint64_t seed) {
        cv::Mat grey, noise(brain.size(), CV_32F);
        cv::GaussianBlur(sharp, grey, cv::Size(), 1.25);
        cv::RNG rng(seed);
        rng.fill(noise, cv::RNG::NORMAL, 0, 0.01);
        return cv::Mat(grey + noise + cv::Scalar(0.05));
    };
    cv::Mat sharp = cv::Mat::zeros(brain.size(), CV_32F);
    sharp.setTo(0.55f, brain);
    sharp(cv::Rect(300, 150, 60, 500)).setTo(0.15f);
    cv::line(sharp, {200, 300}, {460, 420}, cv::Scalar(0), 4);
    const cv::Mat crossing = render(sharp, 41);
    const AtlasExpectation expected{brain, brain, cv::Mat()};
    const DamageParams p;
    ASSERT_GT(p.crackBelowBody, 0) << "on by default";
    // Found, in one or two lines.
    const auto cracks = thinCracks(crossing, brain, expected, none, 1000, p, midline);
    ASSERT_GE(cracks.size(), 1u);
    ASSERT_LE(cracks.size(), 2u);
    double length = 0;
    for (const DamageRegion& d : cracks) {
        length += d.lengthPx;
        EXPECT_TRUE(d.crack);
    }
    // The two stretches in bright tissue (about 110 px each) touch the band; the 66 px across
    // the band itself are not part of them (the band is no tissue level for the closing).
    EXPECT_NEAR(length, 220, 30);
    // Without the valley test the band the crack touches (over 3 x its area) is taken for a
    // dim structure the line belongs to: the crack is lost, as before this rule.
    DamageParams bodyOnly = p;
    bodyOnly.crackBelowBody = 0;
    EXPECT_TRUE(thinCracks(crossing, brain, expected, none, 1000, bodyOnly, midline).empty());
    // A dim tract narrowing to a thin end 5 px wide, at the tract's own level: the thin end is
    // the tract's, no crack, with the rule or without.
    cv::Mat tractSharp = cv::Mat::zeros(brain.size(), CV_32F);
    tractSharp.setTo(0.55f, brain);
    tractSharp(cv::Rect(300, 150, 60, 250)).setTo(0.15f);
    cv::line(tractSharp, {330, 400}, {330, 560}, cv::Scalar(0.15), 5);
    const cv::Mat tract = render(tractSharp, 43);
    EXPECT_TRUE(thinCracks(tract, brain, expected, none, 1000, p, midline).empty());
    EXPECT_TRUE(thinCracks(tract, brain, expected, none, 1000, bodyOnly, midline).empty());
}

TEST(Damage, ABlurredCrackInTheLastPartialTileOfTheBoxIsFound) {
    // The valley closing and the dilations run only on the 64 px tiles that hold a candidate
    // pixel; a crack in the section box's last, partial tile column must be searched too. The
    // brain (1030 px wide) gives a box 1078 px wide (24 px of glass each side): its last tile
    // column starts at image x 1100.
    cv::Mat brain = cv::Mat::zeros({1200, 800}, CV_8U);
    cv::rectangle(brain, cv::Rect(100, 100, 1030, 600), cv::Scalar(255), cv::FILLED);
    const cv::Mat none = cv::Mat::zeros(brain.size(), CV_8U);
    const Midline midline{{615, 0}, {615, 800}};
    cv::Mat sharp = cv::Mat::zeros(brain.size(), CV_32F);
    sharp.setTo(0.55f, brain);
    cv::line(sharp, {1106, 250}, {1106, 500}, cv::Scalar(0), 4);
    cv::Mat grey;
    cv::GaussianBlur(sharp, grey, cv::Size(), 1.25);
    cv::Mat noise(brain.size(), CV_32F);
    cv::RNG rng(23);
    rng.fill(noise, cv::RNG::NORMAL, 0, 0.01);
    grey += noise + cv::Scalar(0.05);
    const AtlasExpectation expected{brain, brain, cv::Mat()};
    const auto cracks = thinCracks(grey, brain, expected, none, 1000, DamageParams{}, midline);
    ASSERT_EQ(cracks.size(), 1u);
    EXPECT_NEAR(cracks[0].lengthPx, 250, 30);
    for (const cv::Point2f& q : cracks[0].polygon)
        EXPECT_NEAR(q.x, 1106, 6);
}

TEST(MaskOps, KthSmallestIsTheValueNthElementGives) {
    cv::RNG rng(31);
    for (const size_t n : {size_t(1), size_t(100), size_t(9000), size_t(300000)}) {
        std::vector<float> v(n);
        for (float& x : v) // negatives, repeats and a wide range of exponents
            x = rng.uniform(0, 4) == 0
                    ? float(rng.uniform(-3, 3))
                    : float(rng.gaussian(1.0) * std::exp(rng.uniform(-8.0, 8.0)));
        for (const size_t k : {size_t(0), n / 2, n - 1}) {
            std::vector<float> a = v, b = v;
            std::nth_element(b.begin(), b.begin() + std::ptrdiff_t(k), b.end());
            EXPECT_EQ(kthSmallest(a, k), b[k]) << n << " values, k " << k;
        }
    }
}

TEST(MaskOps, LabelComponentsGivesWhatOpenCvGives) {
    // Sparse specks, thin lines, blobs touching diagonally, dense noise, a full row and column,
    // masks of odd sizes and views at odd offsets; OpenCV with one thread and with its default.
    cv::RNG rng(47);
    const int threads = cv::getNumThreads();
    int compared = 0;
    for (int t = 0; t < 120; ++t) {
        const int w = rng.uniform(1, 400), h = rng.uniform(1, 300);
        cv::Mat parent = cv::Mat::zeros(h + 3, w + 5, CV_8U);
        cv::Mat m = parent(cv::Rect(t % 5, t % 3, w, h)); // a view, not continuous
        const int kind = t % 4;
        for (int i = rng.uniform(0, 40); i > 0; --i) {
            const cv::Point c(rng.uniform(0, w), rng.uniform(0, h));
            if (kind == 0)
                m.at<uchar>(c) = static_cast<uchar>(rng.uniform(1, 256));
            else if (kind == 1)
                cv::line(m, c, {rng.uniform(0, w), rng.uniform(0, h)}, cv::Scalar(255), 1, 8);
            else
                cv::circle(m, c, rng.uniform(0, 12), cv::Scalar(255), -1);
        }
        if (kind == 3) {
            cv::Mat noise(m.size(), CV_8U);
            rng.fill(noise, cv::RNG::UNIFORM, 0, 256);
            m.setTo(255, noise > 170);
        }
        if (t % 7 == 0 && h > 1 && w > 1) {
            m.row(h - 1).setTo(255);
            m.col(0).setTo(9);
        }
        for (const int n : {1, threads}) {
            cv::setNumThreads(n);
            cv::Mat cvLabels, cvStats, centroids, labels, stats;
            const int expected =
                cv::connectedComponentsWithStats(m, cvLabels, cvStats, centroids, 8, CV_32S);
            ASSERT_EQ(labelComponents(m, labels, stats), expected) << "mask " << t;
            EXPECT_EQ(cv::countNonZero(labels != cvLabels), 0) << "mask " << t;
            ASSERT_EQ(stats.rows, expected);
            if (expected > 1) {
                EXPECT_EQ(
                    cv::countNonZero(stats.rowRange(1, expected) != cvStats.rowRange(1, expected)),
                    0)
                    << "mask " << t;
            }
            EXPECT_EQ(stats.at<int>(0, cv::CC_STAT_AREA), cvStats.at<int>(0, cv::CC_STAT_AREA));
            ++compared;
        }
    }
    cv::setNumThreads(threads);
    EXPECT_EQ(compared, 240);
}

TEST(Damage, AFoldIsADoubledBandBesideAGapAlongTheEdgeAndASliverIsNot) {
    // The atlas expects an ellipse; along its top the section's edge moved in by 12 px.
    const cv::Mat expected = ellipseMask({600, 400}, {300, 200}, {250, 160});
    cv::Mat tissue = expected.clone();
    tissue(cv::Rect(200, 0, 200, 52)).setTo(0);
    cv::Mat labels(expected.size(), CV_32S, cv::Scalar(0));
    labels.setTo(7, expected);
    const DamageParams p;
    // Folded: the 12 px band inside the new edge holds the flap too, twice as bright.
    cv::Mat grey = noisySection(tissue, 0.5f, 0.01f, 11);
    cv::Mat band = cv::Mat::zeros(expected.size(), CV_8U);
    band(cv::Rect(210, 52, 180, 12)).setTo(255);
    grey.setTo(0.95f, band & tissue);
    auto folds = foldBands(grey, tissue, expected, labels, 500, p);
    ASSERT_EQ(folds.size(), 1u);
    EXPECT_EQ(folds[0].kind, DamageKind::Fold);
    EXPECT_NEAR(folds[0].levelShare, 2.0, 0.3);
    EXPECT_GT(folds[0].share, 0.0);
    EXPECT_EQ(toString(DamageKind::Fold), "fold");
    // The same edge with tissue of one level: an outline that did not fit, no fold.
    grey = noisySection(tissue, 0.5f, 0.01f, 12);
    EXPECT_TRUE(foldBands(grey, tissue, expected, labels, 500, p).empty());
}

namespace {
/// The atlas of the misfit tests: a brain (ellipse) with a ventricle left of its centre.
struct MisfitScene {
    cv::Size size{600, 400};
    cv::Mat brain = ellipseMask(size, {300, 200}, {250, 160});
    cv::Mat ventricle = ellipseMask(size, {220, 200}, {30, 45});
    AtlasExpectation expected() const { return {brain & ~ventricle, brain, {}}; }
};
} // namespace

TEST(Damage, AGapBesideTissueWhereTheAtlasExpectsNoneIsAMisfitNotDamage) {
    const MisfitScene scene;
    DamageParams p;
    // The section's ventricle lies 30 px right of the atlas's: glass where the atlas expects
    // tissue on the right, tissue where it expects the ventricle on the left.
    const cv::Mat tissue = scene.brain & ~ellipseMask(scene.size, {250, 200}, {30, 45});
    std::vector<DamageRegion> regions = tissueDamage(tissue, scene.expected(), 500, p);
    ASSERT_FALSE(regions.empty());
    markMisfit(regions, tissue, scene.expected(), 500, p);
    for (const DamageRegion& r : regions) {
        EXPECT_TRUE(r.misfit) << toString(r.kind) << " " << r.share;
        EXPECT_GT(r.excessShare, 0.5);
    }
    const DamageDecision decision = decideDamage(regions, 500, p);
    EXPECT_EQ(decision.verdict, DamageVerdict::CheckRegistration);
    EXPECT_GE(decision.score, p.flagScore);
    // The same gaps without the rule are damage: the verdict above is the rule's doing.
    p.misfitExcess = 1e9;
    markMisfit(regions, tissue, scene.expected(), 500, p);
    EXPECT_EQ(decideDamage(regions, 500, p).verdict, DamageVerdict::Damaged);
}

TEST(Damage, AGapWithTheAtlasFittingAroundItStaysDamage) {
    const MisfitScene scene;
    const DamageParams p;
    // The ventricle where the atlas has it, and a hole of the same size torn beside it.
    const cv::Mat tissue =
        scene.brain & ~scene.ventricle & ~ellipseMask(scene.size, {340, 200}, {30, 45});
    std::vector<DamageRegion> regions = tissueDamage(tissue, scene.expected(), 500, p);
    ASSERT_FALSE(regions.empty());
    markMisfit(regions, tissue, scene.expected(), 500, p);
    for (const DamageRegion& r : regions) {
        EXPECT_FALSE(r.misfit);
        EXPECT_LT(r.excessShare, 0.1);
    }
    EXPECT_EQ(decideDamage(regions, 500, p).verdict, DamageVerdict::Damaged);
    // A bite out of the edge and a thin crack, the outline fitting on either side: damage too.
    cv::Mat bitten = scene.brain & ~scene.ventricle;
    cv::circle(bitten, {300, 360}, 45, cv::Scalar(0), cv::FILLED);
    cv::line(bitten, {400, 150}, {500, 230}, cv::Scalar(0), 4);
    regions = tissueDamage(bitten, scene.expected(), 500, p);
    ASSERT_EQ(regions.size(), 2u);
    markMisfit(regions, bitten, scene.expected(), 500, p);
    for (const DamageRegion& r : regions)
        EXPECT_FALSE(r.misfit) << toString(r.kind) << " excess " << r.excessShare;
    EXPECT_EQ(decideDamage(regions, 500, p).verdict, DamageVerdict::Damaged);
}

TEST(Damage, ACrackIsAMisfitOnlyWhereAThinGapOfTheAtlasLiesBesideIt) {
    const MisfitScene scene;
    const DamageParams p;
    // A thin crack (4 px) whose polygon is drawn by hand, as thinCracks reports it.
    const auto crackRegion = [](cv::Point a, cv::Point b, bool crack) {
        DamageRegion d;
        d.kind = DamageKind::Tear;
        const cv::Point2f u = cv::Point2f(b - a) * (1.0f / float(cv::norm(b - a)));
        const cv::Point2f n(-u.y * 2.0f, u.x * 2.0f);
        d.polygon = {cv::Point2f(a) + n, cv::Point2f(b) + n, cv::Point2f(b) - n,
                     cv::Point2f(a) - n};
        d.lengthPx = cv::norm(b - a);
        d.thicknessPx = 4;
        d.crack = crack;
        return d;
    };
    // The section's outline bulges 30 px beyond the atlas's, 34 px from the crack's mouth: a
    // boundary placed wrong near a gap makes a compact gap a misfit (its half length reaches
    // the bulge), but it cannot have left a line of glass with tissue on both sides.
    const cv::Mat bulged = scene.brain | ellipseMask(scene.size, {550, 230}, {30, 30});
    std::vector<DamageRegion> regions{crackRegion({515, 245}, {415, 285}, false),
                                      crackRegion({515, 245}, {415, 285}, true)};
    markMisfit(regions, bulged, scene.expected(), 500, p);
    EXPECT_TRUE(regions[0].misfit) << "excess " << regions[0].excessShare;
    EXPECT_FALSE(regions[1].misfit) << "excess " << regions[1].excessShare;
    EXPECT_EQ(regions[1].excessShare, 0.0);
    // A fissure of the atlas (12 px wide) with tissue where the atlas puts it, and the
    // section's crack 9 px beside it: the atlas's thin gap placed wrong, a misfit.
    cv::Mat fissure = cv::Mat::zeros(scene.size, CV_8U);
    cv::line(fissure, {380, 100}, {380, 300}, cv::Scalar(255), 12);
    const AtlasExpectation withFissure{scene.brain & ~scene.ventricle & ~fissure, scene.brain, {}};
    const cv::Mat shifted = scene.brain & ~scene.ventricle;
    regions = {crackRegion({389, 110}, {389, 290}, true)};
    markMisfit(regions, shifted, withFissure, 500, p);
    EXPECT_TRUE(regions[0].misfit) << "excess " << regions[0].excessShare;
}

TEST(Damage, ASlitAlongTheMidlineIsTheFissureButAWiderGapThereIsJudged) {
    const auto box = [](float x, float y, float w, float h, double thickness) {
        DamageRegion d;
        d.kind = DamageKind::Tear;
        d.polygon = {{x, y}, {x + w, y}, {x + w, y + h}, {x, y + h}};
        d.lengthPx = std::max(w, h);
        d.thicknessPx = thickness;
        return d;
    };
    // The midline slightly turned, as the affine puts it: x = 300 + 0.05 y.
    const Midline midline{{300, 0}, {320, 400}};
    std::vector<DamageRegion> regions{
        box(308, 150, 5, 60, 5),   // a slit on the midline: the fissure
        box(300, 150, 18, 60, 18), // a wedge as wide as a torn ventricle, on the midline
        box(360, 150, 5, 60, 5),   // a slit 50 px beside the midline
        box(280, 170, 60, 5, 5),   // a slit across the midline
    };
    regions.back().kind = DamageKind::Missing;
    std::vector<DamageRegion> unknown = regions;
    dropAlongMidline(regions, midline, 15, 7);
    ASSERT_EQ(regions.size(), 3u);
    EXPECT_EQ(regions[0].thicknessPx, 18);
    EXPECT_EQ(regions[1].polygon[0].x, 360);
    EXPECT_EQ(regions[2].kind, DamageKind::Missing);
    dropAlongMidline(unknown, Midline{}, 15, 7);
    EXPECT_EQ(unknown.size(), 4u) << "no midline, nothing removed";
}

TEST(Damage, AVentricleWiderThanTheAtlasIsABandAlongItsLumenNotATear) {
    // The atlas: an ellipse of tissue with a ventricle on the midline (x = 300), 10 px wide. The
    // section's ventricle is 16 px wider to the left (a band of glass about 13 px wide beyond the
    // slack, along its left wall); a wedge torn out of its right wall runs away from it.
    const cv::Size size(600, 400);
    const cv::Mat brain = ellipseMask(size, {300, 200}, {250, 160});
    cv::Mat ventricle = cv::Mat::zeros(size, CV_8U);
    cv::rectangle(ventricle, cv::Rect(295, 120, 10, 120), cv::Scalar(255), cv::FILLED);
    const AtlasExpectation expected{brain & ~ventricle, brain, {}};
    cv::Mat tissue = brain.clone();
    cv::rectangle(tissue, cv::Rect(279, 118, 26, 124), cv::Scalar(0), cv::FILLED);
    cv::fillPoly(tissue, std::vector<std::vector<cv::Point>>{{{303, 150}, {400, 160}, {303, 170}}},
                 cv::Scalar(0));
    const DamageParams p;
    std::vector<DamageRegion> regions = tissueDamage(tissue, expected, 500, p);
    int bands = 0, wedges = 0;
    for (const DamageRegion& r : regions) {
        if (r.alongVentricle)
            ++bands;
        else if (r.polygon[0].x > 305)
            ++wedges;
    }
    EXPECT_EQ(bands, 1) << "the wider ventricle's left side";
    EXPECT_EQ(wedges, 1) << "the wedge touches the lumen only at its mouth";
    // On the midline the bands go; the wedge stays.
    std::vector<DamageRegion> onMidline = regions;
    dropAlongMidline(onMidline, Midline{{300, 0}, {300, 400}}, 15, 3);
    ASSERT_EQ(onMidline.size(), std::size_t(wedges));
    EXPECT_FALSE(onMidline[0].alongVentricle);
    // A ventricle band far from the midline is judged as any gap (the mirror rule and the
    // series decide there).
    std::vector<DamageRegion> farAway = regions;
    dropAlongMidline(farAway, Midline{{100, 0}, {100, 400}}, 15, 3);
    EXPECT_EQ(farAway.size(), regions.size());
}

TEST(Damage, ABiteTheWarpFollowedIsAGapAgainstTheAffineAtADeepConcavity) {
    // The atlas under the affine: the whole ellipse. The section lost a bite from its right
    // edge, and the final map bent the atlas onto the cut, so against it nothing is missing.
    const cv::Size size(600, 400);
    const cv::Mat atlas = ellipseMask(size, {300, 200}, {250, 160});
    cv::Mat tissue = atlas.clone();
    cv::circle(tissue, {550, 200}, 60, cv::Scalar(0), cv::FILLED);
    const DamageParams p;
    const AtlasExpectation affine{atlas, atlas, {}};
    const std::vector<DamageRegion> againstAffine = tissueDamage(tissue, affine, 500, p);
    ASSERT_FALSE(againstAffine.empty());
    const std::vector<DamageRegion> found = tissueDamage(tissue, {tissue, tissue, {}}, 500, p);
    EXPECT_TRUE(found.empty()) << "the final map left no gap";
    // Algorithm 2's damage candidates: the bite is a deep concavity without a mirrored partner.
    const Outline outline = tissueOutline(tissue);
    auto concavities = deepConcavities(outline, 0.05 * 500);
    const cv::Matx23d mirror(-1, 0, 600 - 1, 0, 1, 0);
    markSymmetric(concavities, outline, mirror, 500, p);
    const cv::Mat damagedOutline = concavityExclusion(concavities, size, 10);
    ASSERT_GT(damagedOutline.at<uchar>(200, 520), 0);
    const Midline midline{{299.5f, 0}, {299.5f, 400}};
    const std::vector<DamageRegion> bites =
        followedGaps(againstAffine, found, damagedOutline, midline, 15, p);
    ASSERT_EQ(bites.size(), 1u);
    EXPECT_TRUE(bites[0].followed);
    EXPECT_GT(bites[0].openShare, p.alongOutlineShare);
    EXPECT_GT(bites[0].share, 0.02);
    std::vector<DamageRegion> decided = bites;
    EXPECT_EQ(decideDamage(decided, 500, p).verdict, DamageVerdict::Damaged);
    // Not where the outline has no damaged concavity: an outline shaped otherwise than the
    // atlas's.
    EXPECT_TRUE(
        followedGaps(againstAffine, found, cv::Mat::zeros(size, CV_8U), midline, 15, p).empty());
    // Not where the midline runs through it (the cleft between the hemispheres) or passes
    // within the ring.
    EXPECT_TRUE(
        followedGaps(againstAffine, found, damagedOutline, {{550, 0}, {550, 400}}, 15, p).empty());
    EXPECT_TRUE(
        followedGaps(againstAffine, found, damagedOutline, {{480, 0}, {480, 400}}, 15, p).empty());
    // Not twice: the final map's own gap there.
    EXPECT_TRUE(followedGaps(againstAffine, againstAffine, damagedOutline, midline, 15, p).empty());
    // Off: nothing.
    DamageParams off = p;
    off.followedBites = false;
    EXPECT_TRUE(followedGaps(againstAffine, found, damagedOutline, midline, 15, off).empty());
}

TEST(Damage, AShallowBiteAtACutIsMissingTissueNotSlack) {
    // A wide shallow piece lost from the right edge: 20 px deep (under shallowFrac of the width
    // once the slack is taken off) and about seven times as long, so both the slack rule and
    // the band rule take it for an outline that did not fit, unless the outline shows the cut.
    const cv::Size size(600, 400);
    const cv::Mat atlas = ellipseMask(size, {300, 200}, {250, 160});
    const cv::Mat tissue = atlas & ~ellipseMask(size, {560, 200}, {30, 70});
    const double trueArea = cv::countNonZero(atlas & ~tissue);
    const AtlasExpectation expected{atlas, atlas, {}};
    const DamageParams p;
    EXPECT_TRUE(tissueDamage(tissue, expected, 500, p).empty()) << "no cut: slack";
    // Where Algorithm 2 found the outline cut (painted here; concavityExclusion in the
    // registration).
    cv::Mat cut = cv::Mat::zeros(size, CV_8U);
    cv::circle(cut, {545, 200}, 80, cv::Scalar(255), cv::FILLED);
    std::vector<DamageRegion> regions = tissueDamage(tissue, expected, 500, p, {}, {}, cut);
    ASSERT_EQ(regions.size(), 1u);
    const DamageRegion& bite = regions[0];
    EXPECT_TRUE(bite.atCut);
    EXPECT_EQ(bite.kind, DamageKind::Missing) << "a piece lost from the edge, not a tear";
    EXPECT_LT(bite.thicknessPx, p.shallowFrac * 500);
    // Measured up to the expected outline: the slack band went with the piece.
    EXPECT_GT(bite.areaPx, 0.8 * trueArea);
    EXPECT_LT(bite.areaPx, 1.1 * trueArea);
    std::vector<DamageRegion> decided = regions;
    EXPECT_EQ(decideDamage(decided, 500, p).verdict, DamageVerdict::Damaged);
    // A cut elsewhere on the outline says nothing of this stretch.
    cv::Mat elsewhere = cv::Mat::zeros(size, CV_8U);
    cv::circle(elsewhere, {55, 200}, 80, cv::Scalar(255), cv::FILLED);
    EXPECT_TRUE(tissueDamage(tissue, expected, 500, p, {}, {}, elsewhere).empty());
    // Off: slack, as before.
    DamageParams off = p;
    off.bitesAtCuts = false;
    EXPECT_TRUE(tissueDamage(tissue, expected, 500, off, {}, {}, cut).empty());
    // On the midline such a notch is the cleft between the hemispheres.
    std::vector<DamageRegion> onMidline = regions;
    dropAlongMidline(onMidline, Midline{{540, 0}, {540, 400}}, 15, 3);
    EXPECT_TRUE(onMidline.empty());
    std::vector<DamageRegion> awayFromIt = regions;
    dropAlongMidline(awayFromIt, Midline{{300, 0}, {300, 400}}, 15, 3);
    EXPECT_EQ(awayFromIt.size(), 1u);
}

TEST(Damage, TrustedDamageDecidesWhateverMisfitLiesBesideIt) {
    const MisfitScene scene;
    const DamageParams p;
    // The displaced ventricle (misfit) and a fragment pushed off the brain, which lies where
    // the atlas expects no tissue but is damage, not misplaced tissue.
    cv::Mat tissue = scene.brain & ~ellipseMask(scene.size, {250, 200}, {30, 45});
    cv::ellipse(tissue, {60, 40}, {25, 15}, 0, 0, 360, cv::Scalar(255), cv::FILLED);
    std::vector<DamageRegion> regions = tissueDamage(tissue, scene.expected(), 500, p);
    markMisfit(regions, tissue, scene.expected(), 500, p);
    int fragments = 0, misfits = 0;
    for (const DamageRegion& r : regions) {
        fragments += r.kind == DamageKind::Fragment;
        misfits += r.misfit;
        EXPECT_EQ(r.misfit, r.kind != DamageKind::Fragment);
    }
    EXPECT_EQ(fragments, 1);
    EXPECT_GE(misfits, 1);
    EXPECT_EQ(decideDamage(regions, 500, p).verdict, DamageVerdict::Damaged);
    // Neither kind at all: clean.
    std::vector<DamageRegion> none;
    EXPECT_EQ(decideDamage(none, 500, p).verdict, DamageVerdict::Clean);
    EXPECT_EQ(decideDamage(none, 500, p).score, 0.0);
}

TEST(Damage, AGapWithAMirroredTwinIsAnatomyAndALoneOneIsNot) {
    // The atlas frame equals the section's (identity map), the midline at column 100.
    const cv::Size size(200, 120);
    cv::Mat ax(size, CV_32F), ay(size, CV_32F);
    for (int y = 0; y < size.height; ++y)
        for (int x = 0; x < size.width; ++x) {
            ax.at<float>(y, x) = float(x);
            ay.at<float>(y, x) = float(y);
        }
    const cv::Mat known(size, CV_8U, cv::Scalar(255));
    cv::Mat glass = cv::Mat::zeros(size, CV_8U);
    cv::rectangle(glass, cv::Rect(50, 40, 12, 30), cv::Scalar(255), cv::FILLED);  // left
    cv::rectangle(glass, cv::Rect(138, 42, 12, 30), cv::Scalar(255), cv::FILLED); // its twin
    cv::Mat left = cv::Mat::zeros(size, CV_8U);
    cv::rectangle(left, cv::Rect(50, 40, 12, 30), cv::Scalar(255), cv::FILLED);
    // Both ventricles: the twin covers the mirror image (columns 139-150) but for one column
    // and 2 rows.
    EXPECT_NEAR(mirroredShare(left, ax, ay, 100, glass, known, 1), 11.0 / 12 * 28.0 / 30, 1e-9);
    // One-sided: the other side is tissue.
    cv::Mat lone = cv::Mat::zeros(size, CV_8U);
    cv::rectangle(lone, cv::Rect(60, 90, 20, 8), cv::Scalar(255), cv::FILLED);
    EXPECT_EQ(mirroredShare(lone, ax, ay, 100, glass | lone, known, 1), 0.0);
    // Across the midline a gap is its own mirror image: undecided.
    cv::Mat across = cv::Mat::zeros(size, CV_8U);
    cv::rectangle(across, cv::Rect(90, 10, 21, 6), cv::Scalar(255), cv::FILLED);
    EXPECT_EQ(mirroredShare(across, ax, ay, 100, glass | across, known, 1), -1.0);
    // Where the section was not seen, nothing is counted.
    EXPECT_EQ(mirroredShare(left, ax, ay, 100, glass, cv::Mat::zeros(size, CV_8U), 1), -1.0);
}
