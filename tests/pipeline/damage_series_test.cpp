#include "slicestation/pipeline/damage_series.hpp"

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

using namespace slicestation::pipeline;

namespace {
std::vector<cv::Point2f> square(float x, float y, float side) {
    return {{x, y}, {x + side, y}, {x + side, y + side}, {x, y + side}};
}

/// A section of 800 x 800 px registered by a pure affine: 2 image px per atlas px, shifted by 10
/// atlas px (image (180, 180) lands on atlas (100, 100)).
Registration byAffine() {
    Registration reg;
    reg.imageSize = {800, 800};
    reg.workingScale = 1.0;
    reg.atlasFromWorking = cv::Matx23d(0.5, 0, 10, 0, 0.5, 10);
    reg.brainWidthPx = 800;
    return reg;
}

/// An earlier section showing gaps at `polygons` and no glass.
SectionShown gapsAt(AtlasDamageOutlines polygons) {
    return {std::move(polygons), {}};
}

/// A gap of 1% of the tissue (evidence 1.25, score 0.58: flagged on its own).
DamageRegion gap() {
    DamageRegion r;
    r.kind = DamageKind::Missing;
    r.share = 0.01;
    r.lengthPx = 20;
    r.thicknessPx = 20;
    return r;
}
} // namespace

TEST(DamageSeries, AGapAtTheSamePlaceInBothNeighboursIsAnatomy) {
    const DamageParams dp;
    std::vector<DamageRegion> regions{gap()};
    const double alone = damageScore(regions, 400, dp);
    ASSERT_GE(alone, dp.flagScore);
    // Both neighbours show a gap there, a few atlas px off (registration, the next plane).
    const std::vector<AtlasDamageOutlines> neighbours{{square(103, 98, 20)}, {square(96, 104, 20)}};
    const double score =
        applySeriesContext(regions, {square(100, 100, 20)}, neighbours, 400, dp, {});
    EXPECT_DOUBLE_EQ(regions[0].persistence, 1.0);
    EXPECT_DOUBLE_EQ(score, 0.0);
    EXPECT_LT(score, dp.flagScore);
}

TEST(DamageSeries, ATearTheNeighboursDoNotShareKeepsItsScore) {
    const DamageParams dp;
    std::vector<DamageRegion> regions{gap()};
    const double alone = damageScore(regions, 400, dp);
    // The neighbours are damaged elsewhere (60 atlas px away), or not at all.
    const std::vector<AtlasDamageOutlines> neighbours{{square(160, 100, 20)}, {}};
    const double score =
        applySeriesContext(regions, {square(100, 100, 20)}, neighbours, 400, dp, {});
    EXPECT_DOUBLE_EQ(regions[0].persistence, 0.0);
    EXPECT_DOUBLE_EQ(score, alone);
}

TEST(DamageSeries, OneNeighbourOfTwoHalvesTheEvidence) {
    const DamageParams dp;
    std::vector<DamageRegion> regions{gap()};
    const std::vector<AtlasDamageOutlines> neighbours{{square(100, 100, 20)}, {}};
    const double score =
        applySeriesContext(regions, {square(100, 100, 20)}, neighbours, 400, dp, {});
    EXPECT_DOUBLE_EQ(regions[0].persistence, 0.5);
    EXPECT_NEAR(score, scoreFromEvidence(0.5 * 0.01 / dp.damagedShare), 1e-12);
    EXPECT_LT(score, dp.flagScore);
}

TEST(DamageSeries, TheSlackDecidesHowFarTheSamePlaceReaches) {
    const std::vector<AtlasDamageOutlines> neighbours{{square(112, 100, 20)}};
    SeriesContextParams tight;
    tight.slackAtlasPx = 0; // 8 of 20 columns overlap: 0.4 of the area
    tight.samePlaceShare = 0.5;
    tight.window = 1; // one earlier section looked at
    EXPECT_DOUBLE_EQ(persistenceAmong(square(100, 100, 20), neighbours, tight), 0.0);
    SeriesContextParams loose = tight;
    loose.slackAtlasPx = 6; // grown by 6 px the neighbour covers 14 of 20 columns
    EXPECT_DOUBLE_EQ(persistenceAmong(square(100, 100, 20), neighbours, loose), 1.0);
    EXPECT_DOUBLE_EQ(persistenceAmong(square(100, 100, 20), {}, loose), 0.0);
    EXPECT_DOUBLE_EQ(persistenceAmong({}, neighbours, loose), 0.0);
    // With a window of two, one earlier section alone is half the context.
    loose.window = 2;
    EXPECT_DOUBLE_EQ(persistenceAmong(square(100, 100, 20), neighbours, loose), 0.5);
}

TEST(DamageSeries, ARegistrationIsJudgedAgainWithItsEarlierSectionsInAtlasPixels) {
    // A section registered by a pure affine (2 image px per atlas px, shifted by 10 atlas px):
    // a gap and a fragment; the earlier sections show a gap where this gap lands in the atlas.
    Registration reg = byAffine();
    DamageRegion g = gap();
    g.polygon = square(180, 180, 40); // atlas (100, 100) to (120, 120)
    DamageRegion f = gap();
    f.kind = DamageKind::Fragment;
    f.polygon = square(500, 500, 40);
    reg.damage = {g, f};
    const AtlasDamageOutlines atlas = atlasDamageOutlines(reg);
    ASSERT_EQ(atlas.size(), 2u);
    ASSERT_GE(atlas[0].size(), 4u);
    EXPECT_TRUE(atlas[1].empty()) << "a fragment is no anatomy";
    const cv::Rect box = cv::boundingRect(atlas[0]);
    EXPECT_NEAR(box.x, 100, 1);
    EXPECT_NEAR(box.width, 20, 2);
    const DamageParams dp;
    const DamageDecision alone = judgeInSeries(reg, {}, dp, {});
    EXPECT_EQ(alone.verdict, DamageVerdict::Damaged);
    // Both earlier sections show the gap there (a few atlas px off): only the fragment is left.
    const std::vector<SectionShown> earlier{gapsAt({square(103, 98, 20)}),
                                            gapsAt({square(97, 102, 20)})};
    const DamageDecision judged = judgeInSeries(reg, earlier, dp, {});
    EXPECT_DOUBLE_EQ(reg.damage[0].persistence, 1.0);
    EXPECT_DOUBLE_EQ(reg.damage[1].persistence, 0.0);
    EXPECT_NEAR(judged.score, scoreFromEvidence(0.01 / dp.damagedShare), 1e-12);
    EXPECT_DOUBLE_EQ(reg.damageScore, judged.score);
    // A fragment alone still flags (1% of the tissue); without it the section is clean.
    reg.damage.pop_back();
    EXPECT_EQ(judgeInSeries(reg, earlier, dp, {}).verdict, DamageVerdict::Clean);
    EXPECT_FALSE(reg.damaged);
    // Anatomy is continuous: a gap two sections back but not in the one just before is none.
    const std::vector<SectionShown> broken{{}, gapsAt({square(100, 100, 20)})};
    EXPECT_EQ(judgeInSeries(reg, broken, dp, {}).verdict, DamageVerdict::Damaged);
    EXPECT_DOUBLE_EQ(reg.damage[0].persistence, 0.0);
    SeriesContextParams anyOf;
    anyOf.contiguous = false;
    judgeInSeries(reg, broken, dp, anyOf);
    EXPECT_DOUBLE_EQ(reg.damage[0].persistence, 0.5);
    // Only the nearest `window` earlier sections count.
    SeriesContextParams one;
    one.window = 1;
    const std::vector<SectionShown> farther{{}, gapsAt({square(100, 100, 20)})};
    EXPECT_EQ(judgeInSeries(reg, farther, dp, one).verdict, DamageVerdict::Damaged);
}

TEST(DamageSeries, ACrackAtTheSamePlaceLosesItsLengthEvidenceToo) {
    const DamageParams dp;
    DamageRegion crack;
    crack.kind = DamageKind::Tear;
    crack.share = 0.001;
    crack.lengthPx = 80; // 20% of the width: evidence 2
    crack.thicknessPx = 4;
    std::vector<DamageRegion> regions{crack};
    ASSERT_GE(damageScore(regions, 400, dp), dp.flagScore);
    const std::vector<cv::Point2f> line{{100, 100}, {180, 100}, {180, 104}, {100, 104}};
    const double score = applySeriesContext(regions, {line}, {{line}, {line}}, 400, dp, {});
    EXPECT_LT(score, dp.flagScore);
}

TEST(DamageSeries, ABandAlongAVentricleCountsTheNeighboursGlassAGapElseDoesNot) {
    // An earlier section registered by an affine (working px at half the image's size, shifted
    // by 10 atlas px from atlas px) whose glass where its atlas expects tissue is one piece (a
    // ventricle wider than the atlas's, which it did not take for a gap: no damage region) and a
    // piece too small to count.
    Registration earlier;
    earlier.imageSize = {800, 800};
    earlier.workingScale = 0.5;
    earlier.atlasFromWorking = cv::Matx23d(1, 0, 10, 0, 1, 10);
    cv::Mat glass = cv::Mat::zeros(400, 400, CV_8U);
    cv::rectangle(glass, cv::Rect(90, 90, 20, 20), cv::Scalar(255), cv::FILLED);
    cv::rectangle(glass, cv::Rect(200, 200, 3, 3), cv::Scalar(255), cv::FILLED); // too small
    earlier.glassAtlas = glassOutlines(earlier, glass, 50);
    ASSERT_EQ(earlier.glassAtlas.size(), 1u);
    const cv::Rect piece = cv::boundingRect(earlier.glassAtlas[0]);
    EXPECT_NEAR(piece.x, 100, 1); // working (90, 90) + 10 atlas px
    EXPECT_NEAR(piece.y, 100, 1);
    EXPECT_NEAR(piece.width, 20, 2);
    const SectionShown shown = shownInSeries(earlier);
    EXPECT_TRUE(shown.gaps.empty());
    EXPECT_EQ(shown.glass, earlier.glassAtlas);

    // This section's gap lands there in the atlas (image (180, 180) to (220, 220)).
    Registration reg = byAffine();
    DamageRegion g = gap();
    g.polygon = square(180, 180, 40);
    reg.damage = {g};
    const DamageParams dp;
    SeriesContextParams one;
    one.window = 1;
    // A gap that is no band along a ventricle (a wedge torn away from the lumen) counts only
    // the earlier gaps: none.
    EXPECT_EQ(judgeInSeries(reg, {shown}, dp, one).verdict, DamageVerdict::Damaged);
    EXPECT_DOUBLE_EQ(reg.damage[0].persistence, 0.0);
    // A band along a ventricle's lumen counts the earlier glass: the wide ventricle carried on.
    reg.damage[0].alongVentricle = true;
    EXPECT_EQ(judgeInSeries(reg, {shown}, dp, one).verdict, DamageVerdict::Clean);
    EXPECT_DOUBLE_EQ(reg.damage[0].persistence, 1.0);
    // Without the glass it would not (the earlier gaps alone), nor with glass elsewhere.
    EXPECT_EQ(judgeInSeries(reg, {gapsAt({})}, dp, one).verdict, DamageVerdict::Damaged);
    earlier.atlasFromWorking = cv::Matx23d(1, 0, 60, 0, 1, 10);
    earlier.glassAtlas = glassOutlines(earlier, glass, 50);
    EXPECT_EQ(judgeInSeries(reg, {shownInSeries(earlier)}, dp, one).verdict,
              DamageVerdict::Damaged);
}

TEST(DamageSeries, TheGlassKeptIsWhereTheAtlasExpectsTissueNotAVentricleOfTheAtlasSize) {
    // The atlas expects tissue with two ventricles (20 x 20 px); the section shows the left one
    // as the atlas does (a hole 2 px off: registration slack), the right one 16 px wider on
    // its right (a band of glass where the atlas expects tissue), and a cut open to the outside.
    cv::Mat expected = cv::Mat::zeros(200, 300, CV_8U);
    cv::rectangle(expected, cv::Rect(20, 20, 260, 160), cv::Scalar(255), cv::FILLED);
    cv::Mat tissue = expected.clone();
    cv::rectangle(expected, cv::Rect(80, 80, 20, 20), cv::Scalar(0), cv::FILLED);
    cv::rectangle(expected, cv::Rect(200, 80, 20, 20), cv::Scalar(0), cv::FILLED);
    cv::rectangle(tissue, cv::Rect(82, 80, 20, 20), cv::Scalar(0), cv::FILLED);
    cv::rectangle(tissue, cv::Rect(200, 80, 36, 20), cv::Scalar(0), cv::FILLED);
    cv::rectangle(tissue, cv::Rect(20, 140, 40, 6), cv::Scalar(0), cv::FILLED); // open cut
    const cv::Mat glass = glassWhereTissueIsExpected(tissue, expected, 3);
    ASSERT_EQ(glass.size(), tissue.size());
    EXPECT_EQ(cv::countNonZero(glass(cv::Rect(60, 60, 60, 60))), 0)
        << "the ventricle the atlas has, within the slack";
    EXPECT_EQ(cv::countNonZero(glass(cv::Rect(0, 130, 80, 30))), 0) << "not a hole";
    const cv::Rect band = cv::boundingRect(glass);
    EXPECT_EQ(band, cv::Rect(223, 80, 13, 20)) << "the band beyond the slack of the ventricle";
}
