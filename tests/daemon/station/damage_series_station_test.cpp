// Issue 18, item 5: the series as context of the damage decision, end to end through the
// station. A slide of six built-in sections cut 100 um apart (one stack slice each): the first
// four show the same bite out of the dorsal or ventral edge (the generator's "missing" chunk
// with one seed, so it lies at the same atlas place in each: a feature that persists over
// neighbouring sections, as anatomy does), the fifth a tear of its own, the sixth nothing.
// With the run's earlier sections as context the third and fourth (two earlier sections show
// the bite) are no longer flagged; the tear still is.
#include "station_fixture.hpp"

#include <gtest/gtest.h>

#include <fstream>

using namespace slicestation;
using namespace slicestation::daemon;
using namespace slicestation::testing_station;

namespace {

constexpr int kSections = 6;
constexpr double kFirstUm = 3300, kSpacingUm = 100;

const sim::VirtualSlide& persistingSlide() {
    static const sim::VirtualSlide s = [] {
        const char* damage[kSections] = {"missing", "missing", "missing", "missing", "tear", ""};
        const std::uint64_t seed[kSections] = {700, 700, 700, 700, 710, 711};
        std::vector<sim::SlideSectionSpec> sections;
        for (int i = 0; i < kSections; ++i)
            sections.push_back(
                {(kFirstUm + kSpacingUm * i) / kBuiltinLengthUm, damage[i], seed[i]});
        return builtinSlide(std::move(sections), kSections);
    }();
    return s;
}

/// The series context result.json records, or an empty object when there is none.
nlohmann::json contextOf(const nlohmann::json& doc) {
    return doc.value("damage_context", nlohmann::json::object());
}

} // namespace

TEST_F(StationTest, AGapPersistingOverNeighboursIsNotFlaggedWhileAOneOffTearIs) {
    slide_ = &persistingSlide();
    stageLimits_ = kOneRowOfSevenLimits;
    build();
    std::vector<PlanEntry> planned;
    for (int i = 0; i < kSections; ++i)
        planned.push_back(
            entryOf(persistingSlide(), i, static_cast<int>((kFirstUm + kSpacingUm * i) / 100)));
    const RunRecord run = runToTheEnd(planOf(planned, "persisting"));
    EXPECT_EQ(run.doneCount, kSections);
    auto sections = rig_.station->journal().sections(run.id);
    ASSERT_TRUE(sections);
    ASSERT_EQ(sections->size(), std::size_t(kSections));
    std::vector<nlohmann::json> docs;
    for (const SectionRecord& s : *sections) {
        auto regs = rig_.station->journal().registrations(s.id);
        ASSERT_TRUE(regs);
        ASSERT_EQ(regs->size(), 1u) << s.name;
        std::ifstream in(rig_.dir / regs->front().resultPath);
        docs.push_back(nlohmann::json::parse(in, nullptr, false));
        ASSERT_FALSE(docs.back().is_discarded()) << s.name;
        const nlohmann::json c = contextOf(docs.back());
        std::printf("%s %s score %.3f (alone %s %.3f, %d earlier)\n", s.name.c_str(),
                    regs->front().damageVerdict.c_str(), regs->front().damageScore.value_or(-1),
                    c.value("verdict_alone", "?").c_str(), c.value("score_alone", -1.0),
                    c.value("earlier_sections", -1));
        // The journal's record is the judgement with the context, as result.json says.
        EXPECT_EQ(regs->front().damageVerdict, docs.back()["damage_verdict"]) << s.name;
    }
    // The bite alone is damage: flagged in the first section, which has no earlier ones, and
    // in every other one without its context.
    EXPECT_EQ(docs[0]["damage_verdict"], "damaged");
    EXPECT_EQ(contextOf(docs[0]).value("earlier_sections", -1), 0);
    for (const int i : {2, 3}) {
        const auto& d = docs[static_cast<std::size_t>(i)];
        SCOPED_TRACE((*sections)[static_cast<std::size_t>(i)].name);
        EXPECT_EQ(contextOf(d).value("earlier_sections", -1), 2);
        EXPECT_EQ(contextOf(d).value("verdict_alone", ""), "damaged");
        EXPECT_GE(contextOf(d).value("score_alone", 0.0), 0.5);
        // The two earlier sections show it at the same atlas place: not flagged.
        EXPECT_EQ(d["damage_verdict"], "clean") << d["damage_regions"].dump();
        EXPECT_LT(d["damage_score"].get<double>(), 0.5);
        EXPECT_EQ((*sections)[static_cast<std::size_t>(i)].state, SectionState::Registered);
        bool persisted = false;
        for (const auto& r : d["damage_regions"])
            persisted = persisted || r.value("persistence", 0.0) == 1.0;
        EXPECT_TRUE(persisted) << d["damage_regions"].dump();
    }
    // The tear, at a place no earlier section shows damage, is flagged as before.
    const auto& tear = docs[4];
    EXPECT_EQ(tear["damage_verdict"], "damaged") << tear["damage_regions"].dump();
    EXPECT_EQ(contextOf(tear).value("verdict_alone", ""), "damaged");
    EXPECT_EQ(contextOf(tear).value("earlier_sections", -1), 2);
    EXPECT_EQ((*sections)[4].state, SectionState::Damaged);
    // Every registration keeps its gaps, and the glass inside its tissue, in atlas px for the
    // sections after it.
    for (const auto& d : docs) {
        EXPECT_EQ(d.value("damage_atlas", nlohmann::json::array()).size(),
                  d["damage_regions"].size());
        ASSERT_TRUE(d.contains("glass_atlas"));
        EXPECT_TRUE(d["glass_atlas"].is_array());
    }
    // Damaged alerts: the first and the tear (the second, at half its context, may be too);
    // never the third, the fourth or the clean sixth.
    bool tearAlerted = false;
    for (const AlertRecord& a : alertsOf("damaged")) {
        ASSERT_TRUE(a.sectionId.has_value());
        for (const int i : {2, 3, 5})
            EXPECT_NE(*a.sectionId, (*sections)[static_cast<std::size_t>(i)].id) << a.message;
        tearAlerted = tearAlerted || *a.sectionId == (*sections)[4].id;
    }
    EXPECT_TRUE(tearAlerted);
}
