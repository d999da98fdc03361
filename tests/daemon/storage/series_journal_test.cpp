// Issue 19 in the journal: schema version 3 (each registration's planned, matched and found
// plane and the series model's word), the migration of a version-2 file, and the series word
// updated as the model refits.
#include "../../common/journal_fixture.hpp"
#include "slicestation/daemon/storage/journal.hpp"
#include "storage/shipped_schemas.hpp"

#include <gtest/gtest.h>
#include <sqlite3.h>

#include <filesystem>

using namespace slicestation;
using namespace slicestation::daemon;
using slicestation::testing_journal::kShippedVersion1;
using slicestation::testing_journal::kShippedVersion2;

namespace {

class SeriesJournalTest : public testing_journal::JournalDirTest {
protected:
    SeriesJournalTest() : JournalDirTest("series-journal") {}

    /// A run of one section with expected slice 40, captured once; \return the capture id.
    static std::int64_t captured(Journal& j, std::int64_t& sectionId) {
        PlannedSection p;
        p.slideName = "slide-1";
        p.name = "s1";
        p.expectedSlice = 40;
        auto run = j.createRun("r", {}, {}, {p});
        EXPECT_TRUE(run);
        sectionId = j.sections(*run)->front().id;
        CaptureRecord c;
        c.sectionId = sectionId;
        c.imagePath = "x.tif";
        c.umPerPx = 8;
        auto id = j.recordCapture(c);
        EXPECT_TRUE(id);
        return id ? *id : 0;
    }
};

} // namespace

TEST_F(SeriesJournalTest, AVersion2FileMigratesAndItsOldRowsHaveNoPlanes) {
    {
        sqlite3* db = nullptr;
        ASSERT_EQ(sqlite3_open(file().c_str(), &db), SQLITE_OK);
        ASSERT_EQ(sqlite3_exec(db, kShippedVersion1, nullptr, nullptr, nullptr), SQLITE_OK);
        ASSERT_EQ(sqlite3_exec(db, kShippedVersion2, nullptr, nullptr, nullptr), SQLITE_OK)
            << sqlite3_errmsg(db);
        const char* rows =
            "PRAGMA user_version = 2;"
            "INSERT INTO runs VALUES (1,'old','finished','','{}','{}','2026-01-01T00:00:00.000Z',"
            "'','');"
            "INSERT INTO sections VALUES (1,1,0,'slide-1',0,'s1',0,0,0,0,40,'registered','');"
            "INSERT INTO captures VALUES (1,1,1,'x.tif',8,0,0,0,NULL,1,1,1000,1,"
            "'2026-01-01T00:00:01.000Z');"
            "INSERT INTO registrations VALUES (1,1,40,43,0,0,'','',0.9,'r','o','l','{}',"
            "'2026-01-01T00:00:02.000Z',0.1,'clean',0.5);";
        ASSERT_EQ(sqlite3_exec(db, rows, nullptr, nullptr, nullptr), SQLITE_OK)
            << sqlite3_errmsg(db);
        sqlite3_close(db);
    }
    auto j = Journal::open(file());
    ASSERT_TRUE(j) << j.error().message;
    auto regs = (*j)->registrations(1);
    ASSERT_TRUE(regs) << regs.error().message;
    ASSERT_EQ(regs->size(), 1u);
    const RegistrationRecord& r = regs->front();
    EXPECT_EQ(r.atlasSlice, 40);
    EXPECT_EQ(r.matchedSlice, 43);
    EXPECT_DOUBLE_EQ(*r.damageScore, 0.1) << "version 2's columns survive";
    EXPECT_FALSE(r.plannedSlice.has_value()) << "unknown for old rows, not 0";
    EXPECT_FALSE(r.plannedPositionUm.has_value());
    EXPECT_FALSE(r.matchedPositionUm.has_value());
    EXPECT_FALSE(r.foundPositionUm.has_value());
    EXPECT_FALSE(r.series.has_value());
    EXPECT_FALSE(r.foundTiltLrDeg.has_value()) << "version 4's tilt is unknown for old rows";
    const nlohmann::json plane = toJson(r)["plane"];
    EXPECT_TRUE(plane["found"]["tilt_lr_deg"].is_null());
    EXPECT_TRUE(plane["planned"].is_null());
    EXPECT_EQ(plane["matched"]["slice"], 43);
    EXPECT_TRUE(plane["matched"]["position_um"].is_null());
    EXPECT_EQ(plane["found"]["slice"], 40);
    EXPECT_TRUE(plane["series"].is_null());
    // The old row takes a series word; the file is at the current version.
    SeriesPlacement w;
    w.positionUm = 4300;
    w.anomaly = "swapped";
    ASSERT_TRUE((*j)->updateSeries(1, w));
    EXPECT_EQ((*j)->registrations(1)->front().series->anomaly, "swapped");
    EXPECT_TRUE((*j)->checkIntegrity());
    j->reset();
    sqlite3* db = nullptr;
    ASSERT_EQ(sqlite3_open(file().c_str(), &db), SQLITE_OK);
    sqlite3_stmt* st = nullptr;
    sqlite3_prepare_v2(db, "PRAGMA user_version", -1, &st, nullptr);
    ASSERT_EQ(sqlite3_step(st), SQLITE_ROW);
    EXPECT_EQ(sqlite3_column_int(st, 0), Journal::kSchemaVersion);
    sqlite3_finalize(st);
    sqlite3_close(db);
}

TEST_F(SeriesJournalTest, PlanesAndTheSeriesWordAreStoredUpdatedAndBadOnesRefused) {
    auto j = Journal::open(file());
    ASSERT_TRUE(j);
    std::int64_t sectionId = 0;
    const std::int64_t cap = captured(**j, sectionId);
    RegistrationRecord r;
    r.captureId = cap;
    r.atlasSlice = 48;
    r.matchedSlice = 47;
    r.plannedSlice = 40;
    r.plannedPositionUm = 4000;
    r.matchedPositionUm = 4730.5;
    r.foundPositionUm = 4800;
    r.foundTiltLrDeg = 1.75; // registered to a tilted plane (version 4)
    r.foundTiltDvDeg = -0.5;
    SeriesPlacement w;
    w.positionUm = 4760;
    w.slot = 5;
    w.anomaly = "skipped-before";
    w.missingBefore = 1;
    w.tiltLrDeg = 1.5;
    w.tiltDvDeg = -0.5;
    r.series = w;
    auto id = (*j)->recordRegistration(r);
    ASSERT_TRUE(id) << id.error().message;
    auto back = (*j)->registrations(sectionId)->front();
    EXPECT_EQ(back.plannedSlice, 40);
    EXPECT_DOUBLE_EQ(*back.plannedPositionUm, 4000);
    EXPECT_DOUBLE_EQ(*back.matchedPositionUm, 4730.5);
    EXPECT_DOUBLE_EQ(*back.foundPositionUm, 4800);
    ASSERT_TRUE(back.series.has_value());
    EXPECT_DOUBLE_EQ(back.series->positionUm, 4760);
    EXPECT_EQ(back.series->slot, 5);
    EXPECT_EQ(back.series->anomaly, "skipped-before");
    EXPECT_EQ(back.series->missingBefore, 1);
    EXPECT_DOUBLE_EQ(back.series->tiltLrDeg, 1.5);
    EXPECT_DOUBLE_EQ(back.series->tiltDvDeg, -0.5);
    const nlohmann::json plane = planeJson(back);
    EXPECT_EQ(plane["planned"]["slice"], 40);
    EXPECT_EQ(plane["found"]["slice"], 48);
    EXPECT_EQ(plane["found"]["tilted"], true);
    EXPECT_DOUBLE_EQ(plane["found"]["tilt_lr_deg"].get<double>(), 1.75);
    EXPECT_DOUBLE_EQ(plane["found"]["tilt_dv_deg"].get<double>(), -0.5);
    EXPECT_EQ(plane["series"]["anomaly"], "skipped-before");

    // A later section confirms a swap: the word changes, the slice registered to does not.
    w.anomaly = "swapped";
    w.missingBefore = 0;
    w.slot = 4;
    ASSERT_TRUE((*j)->updateSeries(*id, w));
    back = (*j)->registrations(sectionId)->front();
    EXPECT_EQ(back.series->anomaly, "swapped");
    EXPECT_EQ(back.series->slot, 4);
    EXPECT_EQ(back.atlasSlice, 48);

    // Refused: an anomaly the journal does not know (nothing changes), an unknown registration.
    w.anomaly = "sideways";
    auto bad = (*j)->updateSeries(*id, w);
    ASSERT_FALSE(bad);
    EXPECT_EQ(bad.error().code, core::ErrorCode::InvalidArgument);
    EXPECT_EQ((*j)->registrations(sectionId)->front().series->anomaly, "swapped");
    w.anomaly = "none";
    EXPECT_EQ((*j)->updateSeries(*id + 100, w).error().code, core::ErrorCode::NotFound);
    // A registration with an unknown anomaly is not stored at all (one transaction).
    auto rescan = (*j)->requestRescan(sectionId);
    ASSERT_TRUE(rescan) << rescan.error().message;
    CaptureRecord c;
    c.sectionId = sectionId;
    c.imagePath = "y.tif";
    c.umPerPx = 8;
    auto cap2 = (*j)->recordCapture(c);
    ASSERT_TRUE(cap2);
    r.captureId = *cap2;
    r.series->anomaly = "sideways";
    EXPECT_FALSE((*j)->recordRegistration(r));
    EXPECT_EQ((*j)->registrations(sectionId)->size(), 1u);
    EXPECT_EQ((*j)->section(sectionId)->state, SectionState::Captured);
}
