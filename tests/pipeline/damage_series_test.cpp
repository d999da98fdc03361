#include "slicestation/pipeline/damage_series.hpp"

#include <gtest/gtest.h>
#include <opencv2/imgproc.hpp>

using namespace slicestation::pipeline;

namespace {
std::vector<cv::Point2f> square(float x, float y, float side) {
    return {{x, y}, {x + side, y}, {x + side, y + side}, {x, y + side}};
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
    Registration reg;
    reg.imageSize = {800, 800};
    reg.workingScale = 1.0;
    reg.atlasFromWorking = cv::Matx23d(0.5, 0, 10, 0, 0.5, 10);
    reg.brainWidthPx = 800;
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
    const std::vector<AtlasDamageOutlines> earlier{{square(103, 98, 20)}, {square(97, 102, 20)}};
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
    const std::vector<AtlasDamageOutlines> broken{{}, {square(100, 100, 20)}};
    EXPECT_EQ(judgeInSeries(reg, broken, dp, {}).verdict, DamageVerdict::Damaged);
    EXPECT_DOUBLE_EQ(reg.damage[0].persistence, 0.0);
    SeriesContextParams anyOf;
    anyOf.contiguous = false;
    judgeInSeries(reg, broken, dp, anyOf);
    EXPECT_DOUBLE_EQ(reg.damage[0].persistence, 0.5);
    // Only the nearest `window` earlier sections count.
    SeriesContextParams one;
    one.window = 1;
    const std::vector<AtlasDamageOutlines> farther{{}, {square(100, 100, 20)}};
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
