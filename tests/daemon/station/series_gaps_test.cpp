// Issue 19: gaps in a series, end to end through the daemon. A section the technician skipped
// (lost while cutting: every later section lies one slot further than the plan says) is one
// atlas_mismatch alert on the section after the gap; a planned section that fails (here blank
// glass where the plan expects tissue) holds its slot and is no skip.
#include "station_fixture.hpp"

#include <gtest/gtest.h>

#include <cstdio>
#include <map>

using namespace slicestation;
using namespace slicestation::daemon;
using namespace slicestation::testing_station;

namespace {

/// Built-in sections cut at `truthUm` (um from the front of the 8000 um brain), in grid cells
/// of `columns` in slide order.
sim::VirtualSlide seriesSlide(const std::vector<double>& truthUm, int columns, std::uint64_t seed) {
    std::vector<sim::SlideSectionSpec> sections;
    for (std::size_t i = 0; i < truthUm.size(); ++i)
        sections.push_back({truthUm[i] / kBuiltinLengthUm, "", seed + i});
    return builtinSlide(std::move(sections), columns);
}

} // namespace

class SeriesGapsTest : public StationTest {
protected:
    /// Registrations of the run's sections by name (each section's only one), printed as
    /// docs/atlas.md quotes them.
    std::map<std::string, RegistrationRecord>
    registrationsOf(std::int64_t runId, const std::map<std::string, double>& truth) {
        std::map<std::string, RegistrationRecord> out;
        auto sections = rig_.station->journal().sections(runId);
        EXPECT_TRUE(sections);
        if (!sections)
            return out;
        for (const SectionRecord& s : *sections) {
            names_[s.id] = s.name;
            auto regs = rig_.station->journal().registrations(s.id);
            EXPECT_TRUE(regs);
            if (!regs || regs->empty()) {
                std::printf("%s %s, no registration\n", s.name.c_str(), toString(s.state));
                continue;
            }
            EXPECT_EQ(regs->size(), 1u) << s.name;
            const RegistrationRecord& r = regs->front();
            std::printf("%s planned %d own %d (%.0f um) series %.0f um %s/%d slot %d registered "
                        "%d truth %.0f\n",
                        s.name.c_str(), r.plannedSlice.value_or(-1), r.matchedSlice.value_or(-1),
                        r.matchedPositionUm.value_or(0), r.series ? r.series->positionUm : 0.0,
                        r.series ? r.series->anomaly.c_str() : "-",
                        r.series ? r.series->missingBefore : -1, r.series ? r.series->slot : -1,
                        r.atlasSlice, truth.count(s.name) ? truth.at(s.name) : -1.0);
            out[s.name] = r;
        }
        return out;
    }
    /// Alerts of `kind` per section name.
    std::map<std::string, int> alertedSections(const std::string& kind,
                                               std::vector<std::string>* messages = nullptr) {
        std::map<std::string, int> out;
        for (const AlertRecord& a : alertsOf(kind)) {
            EXPECT_TRUE(a.sectionId.has_value()) << a.message;
            if (a.sectionId)
                ++out[names_[*a.sectionId]];
            if (messages)
                messages->push_back(a.message);
            std::printf("%s alert: %s\n", kind.c_str(), a.message.c_str());
        }
        return out;
    }
    std::map<std::int64_t, std::string> names_;
};

// The technician lost the fourth cut: the slide holds slots 0, 1, 2, 4, 5, 6, 7 of an 800 um
// series from 1600 um; the plan lists seven sections one slot apart from slice 16.
TEST_F(SeriesGapsTest, ASkippedSectionIsRecordedAndAlertedOnceAndTheOthersStayOnTheirPlanes) {
    const std::vector<double> truth = {1600, 2400, 3200, 4800, 5600, 6400, 7200};
    // Seeds 300 + slide index, as the swap test's slide (series_station_test.cpp). With seeds
    // 400 + index (tried first) s1 and s3's own matches were 700 and 300 um off on the built-in
    // atlas, before any series logic (docs/atlas.md, "Skips and failures, end to end").
    static const sim::VirtualSlide slide = seriesSlide(truth, 7, 300);
    slide_ = &slide;
    stageLimits_ = kOneRowOfSevenLimits;
    build();
    std::vector<PlanEntry> planned;
    std::map<std::string, double> truthOf;
    for (std::size_t i = 0; i < truth.size(); ++i) {
        const int slot = static_cast<int>(i);
        planned.push_back(entryOf(slide, slot, 16 + 8 * slot));
        truthOf[planned.back().name] = truth[i];
    }
    const RunRecord run = runToTheEnd(planOf(planned, "series"));
    EXPECT_EQ(run.doneCount, static_cast<int>(truth.size()));

    const auto regs = registrationsOf(run.id, truthOf);
    ASSERT_EQ(regs.size(), truth.size());
    for (const auto& [name, r] : regs) {
        SCOPED_TRACE(name);
        ASSERT_TRUE(r.series.has_value());
        // Every section, the one after the gap included, within two built-in slices of where
        // it was cut (the stack's tolerance; measured: six within 100 um, s7 at the back 175
        // um off by its own match, docs/atlas.md).
        EXPECT_NEAR(r.series->positionUm, truthOf[name], 200.0);
        const bool afterGap = name == "s4";
        EXPECT_EQ(r.series->anomaly, afterGap ? "skipped-before" : "none");
        EXPECT_EQ(r.series->missingBefore, afterGap ? 1 : 0);
        // The cutting sequence runs one slot ahead of the plan from s4 on: those sections are
        // registered to the slice the series found (8 slices past the plan), the others to the
        // planned one.
        const int plannedSlice = r.plannedSlice.value_or(-1);
        const bool ahead = name >= "s4";
        const int found = static_cast<int>(std::lround(r.series->positionUm / 100.0));
        EXPECT_EQ(r.atlasSlice, ahead ? found : plannedSlice);
        EXPECT_NEAR(r.atlasSlice, plannedSlice + (ahead ? 8 : 0), 2);
        EXPECT_EQ(r.warning.empty(), !ahead) << r.warning;
        if (ahead && name != "s4") {
            EXPECT_NE(r.warning.find("skipped before it"), std::string::npos) << r.warning;
        }
    }
    // One alert, on the section after the gap; the sections after it are where the skip puts
    // them, so they raise none.
    std::vector<std::string> messages;
    EXPECT_EQ(alertedSections("atlas_mismatch", &messages),
              (std::map<std::string, int>{{"s4", 1}}));
    ASSERT_EQ(messages.size(), 1u);
    EXPECT_NE(messages[0].find("1 section is missing just before it"), std::string::npos)
        << messages[0];
    EXPECT_TRUE(alertsOf("registration_failed").empty());
    EXPECT_TRUE(rig_.station->journal().checkIntegrity());
}

// The fourth planned section fails (its place on the slide is blank glass: nothing to match or
// register). The model knows the slot was planned: the next section is not reported
// skipped-before and no atlas_mismatch is raised; the failure is its own alert.
TEST_F(SeriesGapsTest, AFailedSectionHoldsItsSlotAndIsNoSkip) {
    // Five sections on two rows of four cells; cell (1, 1) of the second row is blank glass.
    const std::vector<double> truth = {1600, 2400, 3200, 4800, 5600};
    static const sim::VirtualSlide slide = seriesSlide(truth, 4, 500);
    slide_ = &slide;
    stageLimits_ = hw::StageLimits{{0, 70'000}, {0, 40'000}, hw::AxisRange{0, 5'000}};
    build();
    const auto& c = slide.sections;
    const double blankX = c[1].centre.xUm, blankY = c[4].centre.yUm;
    // Cutting order: slots 0..5; slot 3 was planned on the blank cell.
    const std::vector<PlanEntry> planned = {
        {"s1", c[0].centre.xUm, c[0].centre.yUm, 16}, {"s2", c[1].centre.xUm, c[1].centre.yUm, 24},
        {"s3", c[2].centre.xUm, c[2].centre.yUm, 32}, {"s4", blankX, blankY, 40},
        {"s5", c[3].centre.xUm, c[3].centre.yUm, 48}, {"s6", c[4].centre.xUm, c[4].centre.yUm, 56}};
    const std::map<std::string, double> truthOf = {
        {"s1", 1600}, {"s2", 2400}, {"s3", 3200}, {"s5", 4800}, {"s6", 5600}};
    const RunRecord run = runToTheEnd(planOf(planned, "series"));

    const auto regs = registrationsOf(run.id, truthOf);
    auto sections = rig_.station->journal().sections(run.id);
    ASSERT_TRUE(sections);
    for (const SectionRecord& s : *sections)
        EXPECT_EQ(s.state == SectionState::Failed, s.name == "s4") << s.name;
    ASSERT_EQ(regs.size(), truthOf.size());
    for (const auto& [name, r] : regs) {
        SCOPED_TRACE(name);
        ASSERT_TRUE(r.series.has_value());
        EXPECT_NEAR(r.series->positionUm, truthOf.at(name), 100.0);
        EXPECT_EQ(r.series->anomaly, "none");
        EXPECT_EQ(r.series->missingBefore, 0);
        EXPECT_EQ(r.atlasSlice, *r.plannedSlice); // each within the tolerance of its plan
    }
    // s5 follows the failed s4 in the cutting sequence: its slot is s3's plus two.
    ASSERT_TRUE(regs.count("s3") && regs.count("s5"));
    EXPECT_EQ(regs.at("s5").series->slot, regs.at("s3").series->slot + 2);
    EXPECT_TRUE(alertedSections("atlas_mismatch").empty());
    EXPECT_EQ(alertedSections("registration_failed"), (std::map<std::string, int>{{"s4", 1}}));
    EXPECT_TRUE(rig_.station->journal().checkIntegrity());
}

// The section where the plan is right is matched near its planned slice even when the whole
// stack's search would not look there: the quick start's second section (the demo slide's ap
// 0.32, seed 2, cut at slice 25.6 of 80) scores best at slices 25-26, but the search's shortlist
// of the 14 best tissue overlaps on the slowly changing built-in atlas leaves them out, and its
// own match was slice 21 (500 um off, an atlas_mismatch alert) before the daemon had the
// planned slice and its neighbours scored beside the shortlist (docs/atlas.md, "The plan's
// slices are scored in the live match").
TEST_F(SeriesGapsTest, ASectionIsMatchedNearThePlannedSliceTheShortlistLeavesOut) {
    // The demo slide's first four sections (docs/examples/demo-station.toml), the third
    // without its tear, in one row; the demo plan's slices for them.
    constexpr int kCount = 4;
    const double ap[kCount] = {0.25, 0.32, 0.39, 0.46};
    const int plannedSlice[kCount] = {20, 26, 31, 37};
    static const sim::VirtualSlide slide = [&] {
        std::vector<sim::SlideSectionSpec> sections;
        for (int i = 0; i < kCount; ++i)
            sections.push_back({ap[i], "", static_cast<std::uint64_t>(i + 1)});
        return builtinSlide(std::move(sections), kCount);
    }();
    slide_ = &slide;
    stageLimits_ = kOneRowOfSevenLimits;
    build();
    std::vector<PlanEntry> planned;
    std::map<std::string, double> truthOf;
    for (int i = 0; i < kCount; ++i) {
        planned.push_back(entryOf(slide, i, plannedSlice[i]));
        truthOf[planned.back().name] = ap[i] * kBuiltinLengthUm;
    }
    const RunRecord run = runToTheEnd(planOf(planned, "demo-part"));
    EXPECT_EQ(run.doneCount, kCount);
    const auto regs = registrationsOf(run.id, truthOf);
    ASSERT_EQ(regs.size(), std::size_t(kCount));
    for (const auto& [name, r] : regs) {
        SCOPED_TRACE(name);
        // Its own match within one slice (100 um) of where it was cut, and registered to the
        // planned slice.
        ASSERT_TRUE(r.matchedPositionUm.has_value());
        EXPECT_NEAR(*r.matchedPositionUm, truthOf.at(name), 100.0);
        EXPECT_EQ(r.atlasSlice, r.plannedSlice.value_or(-1));
    }
    EXPECT_TRUE(alertedSections("atlas_mismatch").empty());
    EXPECT_TRUE(rig_.station->journal().checkIntegrity());
}
