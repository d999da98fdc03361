// Issue 19, item 4: the daemon registers each section to the plane the run's series model says
// and records the planned and the found plane. A slide of seven built-in sections cut 800 um
// apart, the fifth and sixth mounted swapped; the plan lists them in cutting order.
#include "station_fixture.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <map>

using namespace slicestation;
using namespace slicestation::daemon;
using namespace slicestation::testing_station;

namespace {

// Where each section on the slide was cut (um from the front of the 8000 um built-in brain):
// slots 0..6 of an 800 um series from 1600 um, with slots 4 and 5 mounted swapped.
constexpr double kTruthUm[] = {1600, 2400, 3200, 4000, 5600, 4800, 6400};
constexpr int kSections = 7;

const sim::VirtualSlide& swappedSlide() {
    static const sim::VirtualSlide s = [] {
        std::vector<sim::SlideSectionSpec> sections;
        for (int i = 0; i < kSections; ++i)
            sections.push_back(
                {kTruthUm[i] / kBuiltinLengthUm, "", static_cast<std::uint64_t>(300 + i)});
        return builtinSlide(std::move(sections), kSections);
    }();
    return s;
}

} // namespace

TEST_F(StationTest, TheSeriesModelPlacesEachSectionAndASwapIsRecordedAndAlertedOnce) {
    slide_ = &swappedSlide();
    stageLimits_ = kOneRowOfSevenLimits;
    build();
    // The plan: the sections in cutting order, one slot (800 um = 8 built-in slices) apart.
    std::vector<PlanEntry> planned;
    for (int i = 0; i < kSections; ++i)
        planned.push_back(entryOf(swappedSlide(), i, 16 + 8 * i));
    const RunRecord run = runToTheEnd(planOf(planned, "series"));
    EXPECT_EQ(run.doneCount, kSections);

    auto sections = rig_.station->journal().sections(run.id);
    ASSERT_TRUE(sections);
    ASSERT_EQ(sections->size(), std::size_t(kSections));
    std::map<std::int64_t, std::string> names;
    for (int i = 0; i < kSections; ++i) {
        const SectionRecord& s = (*sections)[static_cast<std::size_t>(i)];
        names[s.id] = s.name;
        SCOPED_TRACE(s.name);
        auto regs = rig_.station->journal().registrations(s.id);
        ASSERT_TRUE(regs);
        ASSERT_EQ(regs->size(), 1u);
        const RegistrationRecord& r = regs->front();
        // The figures docs/atlas.md quotes (planned, own match, series, registered, truth).
        std::printf("%s planned %d own %d (%.0f um) series %.0f um %s registered %d truth %.0f\n",
                    s.name.c_str(), r.plannedSlice.value_or(-1), r.matchedSlice.value_or(-1),
                    r.matchedPositionUm.value_or(0), r.series ? r.series->positionUm : 0.0,
                    r.series ? r.series->anomaly.c_str() : "-", r.atlasSlice, kTruthUm[i]);
        // Planned: the plan's slice and its position.
        ASSERT_TRUE(r.plannedSlice.has_value());
        EXPECT_EQ(*r.plannedSlice, 16 + 8 * i);
        EXPECT_DOUBLE_EQ(r.plannedPositionUm.value_or(-1), 100.0 * (16 + 8 * i));
        // Found: the series' position, within two built-in slices of where it was cut, and the
        // slice registered to is the stack's nearest to it.
        ASSERT_TRUE(r.series.has_value());
        ASSERT_TRUE(r.matchedSlice.has_value());
        ASSERT_TRUE(r.matchedPositionUm.has_value());
        EXPECT_NEAR(r.series->positionUm, kTruthUm[i], 200.0);
        // Registered to the slice the series says when it is beyond the tolerance (2 slices)
        // from the planned one, else to the planned one.
        const int found = static_cast<int>(std::lround(r.series->positionUm / 100.0));
        EXPECT_EQ(r.atlasSlice, std::abs(found - *r.plannedSlice) > 2 ? found : *r.plannedSlice);
        EXPECT_DOUBLE_EQ(r.foundPositionUm.value_or(-1), 100.0 * r.atlasSlice);
        // The series' word, as confirmed by the section after it (the last by itself).
        const bool swapped = i == 4 || i == 5;
        EXPECT_EQ(r.series->anomaly, swapped ? "swapped" : "none");
        // A found plane off the plan is the registration's warning.
        EXPECT_EQ(r.warning.empty(), !swapped) << r.warning;
        // result.json records both planes beside the slice registered to.
        std::ifstream in(rig_.dir / r.resultPath);
        const auto doc = nlohmann::json::parse(in, nullptr, false);
        ASSERT_FALSE(doc.is_discarded());
        EXPECT_EQ(doc["plane"]["planned"]["slice"], 16 + 8 * i);
        EXPECT_EQ(doc["plane"]["found"]["slice"], r.atlasSlice);
        EXPECT_EQ(doc["atlas"]["stack"]["index"], r.atlasSlice);
        // GET /api/sections/{id}: the planes of the latest registration.
        auto detail = rig_.station->sectionDetail(s.id);
        ASSERT_TRUE(detail);
        EXPECT_EQ((*detail)["plane"]["planned"]["slice"], 16 + 8 * i);
        EXPECT_EQ((*detail)["plane"]["found"]["slice"], r.atlasSlice);
        EXPECT_EQ((*detail)["plane"]["series"]["anomaly"], r.series->anomaly);
    }
    // One atlas_mismatch alert for each of the two swapped sections, none for the others.
    std::map<std::string, int> alerted;
    for (const AlertRecord& a : alertsOf("atlas_mismatch")) {
        ASSERT_TRUE(a.sectionId.has_value());
        ++alerted[names[*a.sectionId]];
        EXPECT_NE(a.message.find("swapped with its neighbour"), std::string::npos) << a.message;
    }
    EXPECT_EQ(alerted, (std::map<std::string, int>{{"s5", 1}, {"s6", 1}}));
    EXPECT_TRUE(rig_.station->journal().checkIntegrity());
}
