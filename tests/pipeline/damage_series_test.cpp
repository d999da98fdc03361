#include "slicestation/pipeline/damage_series.hpp"

#include <gtest/gtest.h>

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
    EXPECT_DOUBLE_EQ(persistenceAmong(square(100, 100, 20), neighbours, tight), 0.0);
    SeriesContextParams loose = tight;
    loose.slackAtlasPx = 6; // grown by 6 px the neighbour covers 14 of 20 columns
    EXPECT_DOUBLE_EQ(persistenceAmong(square(100, 100, 20), neighbours, loose), 1.0);
    EXPECT_DOUBLE_EQ(persistenceAmong(square(100, 100, 20), {}, loose), 0.0);
    EXPECT_DOUBLE_EQ(persistenceAmong({}, neighbours, loose), 0.0);
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
