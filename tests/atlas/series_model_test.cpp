// The series model on synthetic positions with known spacing, noise, skips, swaps and wrong
// matches (pure arithmetic: milliseconds).
#include "slicestation/pipeline/series_matching.hpp"
#include "slicestation/pipeline/series_model.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <random>

using namespace slicestation::pipeline;

namespace {

/// Observations at origin + spacing x slot plus Gaussian noise.
std::vector<SeriesObservation> series(const std::vector<int>& slots, double origin, double spacing,
                                      double noiseUm, unsigned seed) {
    std::mt19937 rng(seed);
    std::normal_distribution<double> noise(0, noiseUm);
    std::vector<SeriesObservation> obs;
    for (int s : slots) {
        SeriesObservation o;
        o.positionUm = origin + spacing * s + (noiseUm > 0 ? noise(rng) : 0);
        o.score = 0.3;
        obs.push_back(o);
    }
    return obs;
}

std::vector<int> range(int n) {
    std::vector<int> v;
    for (int i = 0; i < n; ++i)
        v.push_back(i);
    return v;
}

} // namespace

TEST(SeriesModel, FitsACleanSeries) {
    const auto obs = series(range(20), 1500, 320, 40, 1);
    for (double prior : {0.0, 300.0}) {
        SeriesModelOptions o;
        o.intervalUm = prior;
        auto f = fitSeries(obs, o);
        ASSERT_TRUE(f.ok()) << f.error().message;
        EXPECT_NEAR(f->spacingUm, 320, 8) << "prior " << prior;
        EXPECT_NEAR(f->originUm, 1500, 60);
        EXPECT_EQ(f->inliers, 20);
        for (size_t k = 0; k < obs.size(); ++k) {
            EXPECT_EQ(f->sections[k].slot, int(k));
            EXPECT_EQ(f->sections[k].anomaly, SeriesAnomaly::None) << k;
        }
        EXPECT_NEAR(f->predictUm(20), 1500 + 320 * 20, 100);
    }
}

// A swap is two sections mounted in each other's place: the pair steps back by about a spacing.
// Two neighbours 0.3 spacing either side of the middle between their slots have exchanged slots
// too (each is nearer the other's), but a step back of 0.4 spacing is one of them matched wrong
// (the gerbi series' sections 20 and 21 looked like this), not an exchange.
TEST(SeriesModel, ASwapStepsBackByAboutASpacing) {
    auto obs = series(range(20), 2000, 300, 0, 1);
    obs[9].positionUm = 2000 + 300 * 9.7;
    obs[10].positionUm = 2000 + 300 * 9.3;
    SeriesModelOptions o;
    o.intervalUm = 300;
    auto near = fitSeries(obs, o);
    ASSERT_TRUE(near.ok()) << near.error().message;
    EXPECT_EQ(near->sections[9].slot, 10);
    EXPECT_EQ(near->sections[10].slot, 9);
    EXPECT_NE(near->sections[9].anomaly, SeriesAnomaly::Swapped);
    EXPECT_NE(near->sections[10].anomaly, SeriesAnomaly::Swapped);
    // Exchanged in full, they are a swap.
    obs[9].positionUm = 2000 + 300 * 10.1;
    obs[10].positionUm = 2000 + 300 * 8.9;
    auto swapped = fitSeries(obs, o);
    ASSERT_TRUE(swapped.ok());
    EXPECT_EQ(swapped->sections[9].anomaly, SeriesAnomaly::Swapped);
    EXPECT_EQ(swapped->sections[10].anomaly, SeriesAnomaly::Swapped);
}

TEST(SeriesModel, ReportsSkipSwapAndWrongMatch) {
    // Slot 6 lost, slots 11 and 12 swapped, and section 16's match 2.5 spacings off the line
    // (half way between two slots: a wrong match, not a section from another slot) with a third
    // of the usual score: not believed, it is placed on the line between its neighbours.
    std::vector<int> slots;
    for (int s = 0; s < 22; ++s)
        if (s != 6)
            slots.push_back(s);
    std::swap(slots[10], slots[11]);
    auto obs = series(slots, 2000, 300, 30, 2);
    obs[16].positionUm = 2000 + 300 * (17 + 2.5);
    obs[16].score = 0.1;
    SeriesModelOptions o;
    o.intervalUm = 280;
    auto f = fitSeries(obs, o);
    ASSERT_TRUE(f.ok()) << f.error().message;
    EXPECT_NEAR(f->spacingUm, 300, 8);
    for (size_t k = 0; k < obs.size(); ++k) {
        const SeriesAnomaly want = k == 6               ? SeriesAnomaly::Skipped
                                   : k == 10 || k == 11 ? SeriesAnomaly::Swapped
                                   : k == 16            ? SeriesAnomaly::Placed
                                                        : SeriesAnomaly::None;
        EXPECT_EQ(f->sections[k].anomaly, want) << "section " << k;
    }
    EXPECT_EQ(f->sections[6].missingBefore, 1);
    EXPECT_EQ(f->sections[10].slot, 12);
    EXPECT_EQ(f->sections[11].slot, 11);
    EXPECT_FALSE(f->sections[16].inlier);
    EXPECT_EQ(f->inliers, 20);
    // The series' answer for it is the line's position at the slot after its predecessor's.
    EXPECT_EQ(f->sections[16].slot, 17);
    EXPECT_DOUBLE_EQ(f->sections[16].positionUm, f->positionOfSlot(17));
    EXPECT_DOUBLE_EQ(f->sections[3].positionUm, obs[3].positionUm);

    // The same wrong match with the usual score is an alert, not placed.
    obs[16].score = 0.3;
    auto confident = fitSeries(obs, o);
    ASSERT_TRUE(confident.ok());
    EXPECT_EQ(confident->sections[16].anomaly, SeriesAnomaly::OffLine);
    EXPECT_DOUBLE_EQ(confident->sections[16].positionUm, obs[16].positionUm);
    // And with placing turned off.
    obs[16].score = 0.1;
    o.placeScoreRatio = 0;
    auto never = fitSeries(obs, o);
    ASSERT_TRUE(never.ok());
    EXPECT_EQ(never->sections[16].anomaly, SeriesAnomaly::OffLine);
}

TEST(SeriesModel, WeakMatchesThatBreakTheOrderArePlacedInOrder) {
    // Sections 5 and 6 (slots 5, 6) matched weakly two and four slots back, onto slots 3 and 2:
    // placed on slots 5 and 6, in order, and no skip reported around them.
    auto obs = series(range(16), 1000, 300, 20, 7);
    obs[5].positionUm = 1000 + 300 * 3 + 10;
    obs[5].score = 0.05;
    obs[6].positionUm = 1000 + 300 * 2 - 10;
    obs[6].score = 0.08;
    SeriesModelOptions o;
    o.intervalUm = 300;
    auto f = fitSeries(obs, o);
    ASSERT_TRUE(f.ok());
    for (size_t k = 0; k < obs.size(); ++k) {
        const SeriesAnomaly want = k == 5 || k == 6 ? SeriesAnomaly::Placed : SeriesAnomaly::None;
        EXPECT_EQ(f->sections[k].anomaly, want) << "section " << k;
        EXPECT_EQ(f->sections[k].slot, int(k)) << k;
        if (k > 0) {
            EXPECT_GT(f->sections[k].positionUm, f->sections[k - 1].positionUm) << k;
        }
    }
    EXPECT_EQ(f->inliers, 14);
}

TEST(SeriesModel, ASectionFarOutOfOrderIsReported) {
    // Slot 11's section mounted fifth: 0 1 2 3 11 4 5 ... 10 12 ...
    std::vector<int> slots = range(16);
    slots.erase(slots.begin() + 11);
    slots.insert(slots.begin() + 4, 11);
    const auto obs = series(slots, 1000, 250, 20, 3);
    auto f = fitSeries(obs, {});
    ASSERT_TRUE(f.ok());
    EXPECT_NEAR(f->spacingUm, 250, 6);
    EXPECT_EQ(f->sections[4].anomaly, SeriesAnomaly::OutOfOrder);
    EXPECT_EQ(f->sections[4].slot, 11);
    // Its own place, before section 12, is reported empty too: from positions alone a section
    // mounted far away and a wrong match that sits on a lost slot look the same.
    EXPECT_EQ(f->sections[12].anomaly, SeriesAnomaly::Skipped);
    for (size_t k = 0; k < obs.size(); ++k) {
        if (k != 4 && k != 12) {
            EXPECT_EQ(f->sections[k].anomaly, SeriesAnomaly::None) << k;
        }
    }
}

TEST(SeriesModel, AWeakSectionWithNoFreeSlotStaysOutOfOrder) {
    // As above, but the section's match scores a fifth of the others'. Its neighbours in the run
    // hold consecutive slots (3 and 4), so there is no place between them to put it: it stays
    // out of order rather than pushing the run.
    std::vector<int> slots = range(16);
    slots.erase(slots.begin() + 11);
    slots.insert(slots.begin() + 4, 11);
    auto obs = series(slots, 1000, 250, 20, 3);
    obs[4].score = 0.06;
    auto f = fitSeries(obs, {});
    ASSERT_TRUE(f.ok());
    EXPECT_EQ(f->sections[4].anomaly, SeriesAnomaly::OutOfOrder);
    EXPECT_EQ(f->sections[4].slot, 11);
    EXPECT_DOUBLE_EQ(f->sections[4].positionUm, obs[4].positionUm);
}

TEST(SeriesModel, BackToFrontGivesANegativeSpacing) {
    const auto obs = series(range(12), 9000, -300, 25, 4);
    SeriesModelOptions o;
    o.intervalUm = 300;
    auto f = fitSeries(obs, o);
    ASSERT_TRUE(f.ok());
    EXPECT_NEAR(f->spacingUm, -300, 8);
    for (size_t k = 0; k < obs.size(); ++k)
        EXPECT_EQ(f->sections[k].anomaly, SeriesAnomaly::None) << k;
}

TEST(SeriesModel, TiltIsTheRobustMedianOfTheInliers) {
    auto obs = series(range(15), 1000, 300, 20, 5);
    std::mt19937 rng(9);
    std::normal_distribution<double> noise(0, 1.0);
    for (auto& o : obs) {
        o.tiltEstimated = true;
        o.tiltColumnsDeg = 2.0 + noise(rng);
        o.tiltRowsDeg = -1.0 + noise(rng);
    }
    obs[3].tiltColumnsDeg = 40; // a wild estimate does not move a median
    auto f = fitSeries(obs, {});
    ASSERT_TRUE(f.ok());
    EXPECT_EQ(f->tiltSections, 15);
    EXPECT_NEAR(f->tiltColumnsDeg, 2.0, 0.6);
    EXPECT_NEAR(f->tiltRowsDeg, -1.0, 0.6);
}

TEST(SeriesModel, FewSectionsAndBadInput) {
    SeriesModelOptions o;
    o.intervalUm = 300;
    auto one = fitSeries(series({0}, 4000, 300, 0, 1), o);
    ASSERT_TRUE(one.ok());
    EXPECT_DOUBLE_EQ(one->spacingUm, 300);
    EXPECT_DOUBLE_EQ(one->predictUm(1), 4300);

    EXPECT_FALSE(fitSeries({}, o).ok());
    auto bad = series(range(4), 0, 300, 0, 1);
    bad[2].positionUm = std::nan("");
    const auto e = fitSeries(bad, o);
    ASSERT_FALSE(e.ok());
    EXPECT_NE(e.error().message.find("section 2"), std::string::npos) << e.error().message;
    SeriesModelOptions neg;
    neg.intervalUm = -5;
    EXPECT_FALSE(fitSeries(series(range(4), 0, 300, 0, 1), neg).ok());
    SeriesModelOptions slack;
    slack.spacingSlack = 1.5;
    EXPECT_FALSE(fitSeries(series(range(4), 0, 300, 0, 1), slack).ok());
    SeriesModelOptions place;
    place.placeScoreRatio = -0.5;
    const auto p = fitSeries(series(range(4), 0, 300, 0, 1), place);
    ASSERT_FALSE(p.ok());
    EXPECT_EQ(p.error().code, slicestation::core::ErrorCode::InvalidArgument);
}

TEST(SeriesModel, AWrongMatchOnTheLostSlotDoesNotHideTheSkip) {
    // Slot 8 lost; section 5's match lands on slot 8 (a wrong match that sits on a slot).
    std::vector<int> slots;
    for (int s = 0; s < 20; ++s)
        if (s != 8)
            slots.push_back(s);
    auto obs = series(slots, 1800, 300, 15, 6);
    obs[5].positionUm = 1800 + 300 * 8 + 5;
    SeriesModelOptions o;
    o.intervalUm = 300;
    auto f = fitSeries(obs, o);
    ASSERT_TRUE(f.ok());
    EXPECT_EQ(f->sections[5].anomaly, SeriesAnomaly::OutOfOrder);
    EXPECT_EQ(f->sections[8].anomaly, SeriesAnomaly::Skipped);
    EXPECT_EQ(f->sections[8].missingBefore, 1);
}

// The series' Viterbi pass (SeriesMatcher::finish, last step): each section's options are its own
// match (value 1) and other slices it scored, relative to it; a step's cost is 0.1 x the squared
// deviation from the spacing, in spacings, capped at 4.
namespace {
std::vector<std::vector<SeriesOption>> ownOnly(const std::vector<double>& positions) {
    std::vector<std::vector<SeriesOption>> o;
    for (double p : positions)
        o.push_back({{p, 1.0}});
    return o;
}
} // namespace

TEST(SeriesChoice, AConfidentWrongMatchTakesTheSlotItsNeighboursLeave) {
    // Section 2's own match lies four slots on (as gerbi 21 lay two slots back); at its regular
    // place it scores 70% of that. Its two steps cost 0.4 each, more than the 0.3 it loses.
    auto o = ownOnly({0, 300, 1500, 900, 1200});
    o[2].push_back({600, 0.7});
    o[2].push_back({1800, 0.9});
    const auto pick = chooseAlongSeries(o, 300, 0.1, 4);
    ASSERT_EQ(pick.size(), 5u);
    EXPECT_EQ(pick[2], 1u);
    for (size_t k : {0u, 1u, 3u, 4u})
        EXPECT_EQ(pick[k], 0u) << k;
    // Weaker at the regular place than the steps cost: it stays where it matched.
    o[2][1].value = 0.15;
    EXPECT_EQ(chooseAlongSeries(o, 300, 0.1, 4)[2], 0u);
}

TEST(SeriesChoice, ARealSwapAndARealSkipStay) {
    // Swapped pair (sections 2 and 3): 1 + 4 + 1 tenths; each scores half at the regular place.
    auto swap = ownOnly({0, 300, 900, 600, 1200});
    swap[2].push_back({600, 0.5});
    swap[3].push_back({900, 0.5});
    EXPECT_EQ(chooseAlongSeries(swap, 300, 0.1, 4), (std::vector<size_t>{0, 0, 0, 0, 0}));
    // One lost section before section 3: one tenth, against 40% of the score.
    auto skip = ownOnly({0, 300, 600, 1200, 1500});
    skip[3].push_back({900, 0.6});
    EXPECT_EQ(chooseAlongSeries(skip, 300, 0.1, 4), (std::vector<size_t>{0, 0, 0, 0, 0}));
    // Cut back to front: a negative spacing is the same regular step.
    auto back = ownOnly({1200, 900, 0, 300, 0});
    back[2].push_back({600, 0.7});
    EXPECT_EQ(chooseAlongSeries(back, -300, 0.1, 4)[2], 1u);
}

TEST(SeriesChoice, NothingToChooseFrom) {
    EXPECT_TRUE(chooseAlongSeries({}, 300, 0.1, 4).empty());
    EXPECT_TRUE(chooseAlongSeries(ownOnly({0, 300}), 0, 0.1, 4).empty());
    EXPECT_TRUE(chooseAlongSeries({{{0, 1}}, {}}, 300, 0.1, 4).empty());
}
