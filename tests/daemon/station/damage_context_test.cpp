// Issue 18, item 5: the damage decision's series context, read back from the journal. Every
// result document keeps its gaps in atlas px; a section's context is the latest registrations
// of the sections before it in the plan's order, nearest first, unregistered ones passed over.
#include "slicestation/daemon/station/damage_context.hpp"

#include "../../common/journal_fixture.hpp"

#include <gtest/gtest.h>

#include <filesystem>

using namespace slicestation;
using namespace slicestation::daemon;

namespace {

std::vector<cv::Point2f> square(float x, float y, float side) {
    return {{x, y}, {x + side, y}, {x + side, y + side}, {x, y + side}};
}

class DamageContextTest : public testing_journal::JournalDirTest {
protected:
    DamageContextTest() : JournalDirTest("damage-context") {}
    void SetUp() override {
        JournalDirTest::SetUp();
        auto j = Journal::open(file());
        ASSERT_TRUE(j) << j.error().message;
        journal_ = std::move(*j);
    }
    void TearDown() override {
        journal_.reset();
        JournalDirTest::TearDown();
    }
    /// Journals a registration of `sectionId` whose result keeps `outlines`.
    void registered(std::int64_t sectionId, const pipeline::AtlasDamageOutlines& outlines,
                    const pipeline::AtlasDamageOutlines& glass = {}) {
        RegistrationRecord r;
        r.captureId = journal_->captures(sectionId)->back().id;
        r.damageScore = 0;
        r.flagScore = 0.5;
        r.damageVerdict = "clean";
        r.result = {{"damage_atlas", atlasOutlinesJson(outlines)}};
        if (!glass.empty())
            r.result["glass_atlas"] = atlasOutlinesJson(glass);
        ASSERT_TRUE(journal_->recordRegistration(r));
    }
    std::unique_ptr<Journal> journal_;
};

} // namespace

TEST_F(DamageContextTest, OutlinesSurviveTheResultDocument) {
    const pipeline::AtlasDamageOutlines outlines{square(10, 20, 5), {}, square(1.5f, 2.5f, 3)};
    const nlohmann::json doc = {{"damage_atlas", atlasOutlinesJson(outlines)}};
    EXPECT_EQ(atlasOutlinesFromResult(nlohmann::json::parse(doc.dump())), outlines);
    // Registrations journalled before the series context have none; malformed points are
    // dropped, not fatal.
    EXPECT_TRUE(atlasOutlinesFromResult(nlohmann::json::object()).empty());
    const auto odd = atlasOutlinesFromResult({{"damage_atlas", {{{1, 2}, "x", {3}}, 7}}});
    ASSERT_EQ(odd.size(), 2u);
    EXPECT_EQ(odd[0], (std::vector<cv::Point2f>{{1, 2}}));
    EXPECT_TRUE(odd[1].empty());
}

TEST_F(DamageContextTest, TheEarlierSectionsAreReadBackNearestFirstSkippingUnregisteredOnes) {
    const auto [runId, ids] = testing_journal::runWithCaptures(*journal_, 5);
    registered(ids[0], {square(0, 0, 4)});
    registered(ids[1], {square(10, 0, 4)});
    // ids[2] is not registered (pending, failed); ids[1] is rescanned and registered again:
    // the latest registration counts.
    ASSERT_TRUE(journal_->requestRescan(ids[1]));
    CaptureRecord again;
    again.sectionId = ids[1];
    again.imagePath = "y.tif";
    again.umPerPx = 8;
    ASSERT_TRUE(journal_->recordCapture(again));
    registered(ids[1], {square(20, 0, 4)});
    const auto forFourth = earlierDamageOutlines(*journal_, runId, ids[3], 2);
    ASSERT_EQ(forFourth.size(), 2u);
    EXPECT_EQ(forFourth[0].gaps, (pipeline::AtlasDamageOutlines{square(20, 0, 4)}));
    EXPECT_EQ(forFourth[1].gaps, (pipeline::AtlasDamageOutlines{square(0, 0, 4)}));
    EXPECT_TRUE(forFourth[0].glass.empty()) << "journalled before the glass was kept: none";
    // At most the window; nothing before the first section; a section after the ones asked
    // about plays no part.
    registered(ids[4], {square(30, 0, 4)});
    EXPECT_EQ(earlierDamageOutlines(*journal_, runId, ids[3], 1).size(), 1u);
    EXPECT_TRUE(earlierDamageOutlines(*journal_, runId, ids[0], 2).empty());
    const auto forSecond = earlierDamageOutlines(*journal_, runId, ids[1], 2);
    ASSERT_EQ(forSecond.size(), 1u);
    EXPECT_EQ(forSecond[0].gaps, (pipeline::AtlasDamageOutlines{square(0, 0, 4)}));
    // A journal opened again (a restart) gives the same context.
    journal_.reset();
    auto reopened = Journal::open(file());
    ASSERT_TRUE(reopened);
    journal_ = std::move(*reopened);
    EXPECT_EQ(earlierDamageOutlines(*journal_, runId, ids[3], 2), forFourth);
}

TEST_F(DamageContextTest, AnEarlierSectionShowsItsGapsAndItsGlass) {
    const auto [runId, ids] = testing_journal::runWithCaptures(*journal_, 2);
    // The earlier section: one gap and two holes of glass it did not take for gaps.
    registered(ids[0], {square(0, 0, 4)}, {square(50, 50, 8), square(70, 10, 6)});
    const auto forSecond = earlierDamageOutlines(*journal_, runId, ids[1], 2);
    ASSERT_EQ(forSecond.size(), 1u);
    EXPECT_EQ(forSecond[0].gaps, (pipeline::AtlasDamageOutlines{square(0, 0, 4)}));
    EXPECT_EQ(forSecond[0].glass,
              (pipeline::AtlasDamageOutlines{square(50, 50, 8), square(70, 10, 6)}));
    const nlohmann::json doc = {{"glass_atlas", atlasOutlinesJson({square(1, 2, 3)})}};
    EXPECT_EQ(atlasOutlinesFromResult(doc, "glass_atlas"),
              (pipeline::AtlasDamageOutlines{square(1, 2, 3)}));
    EXPECT_TRUE(atlasOutlinesFromResult(doc).empty()) << "no gaps in it";
}
