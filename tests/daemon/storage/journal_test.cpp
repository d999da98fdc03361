// The SQLite journal on real files: states, transactions, rescans, alerts, migrations, bad files.
#include "../../common/journal_fixture.hpp"
#include "full_disk_vfs.hpp"
#include "slicestation/daemon/storage/journal.hpp"

#include <gtest/gtest.h>
#include <sqlite3.h>

#include <cerrno>
#include <filesystem>
#include <fstream>

using namespace slicestation;
using namespace slicestation::daemon;

namespace {

class JournalTest : public testing_journal::JournalDirTest {
protected:
    JournalTest() : JournalDirTest("journal") {}

    static std::vector<PlannedSection> twoSlides() {
        std::vector<PlannedSection> v;
        for (int s = 0; s < 2; ++s)
            for (int i = 0; i < 3; ++i) {
                PlannedSection p;
                p.slideIndex = s;
                p.slideName = "slide-" + std::to_string(s + 1);
                p.index = i;
                p.name = "s" + std::to_string(i + 1);
                p.xUm = 1000.0 * (i + 1);
                p.yUm = 5000.0 * (s + 1);
                p.expectedSlice = 10 + s * 3 + i;
                v.push_back(p);
            }
        return v;
    }
    static CaptureRecord captureOf(std::int64_t sectionId) {
        CaptureRecord c;
        c.sectionId = sectionId;
        c.imagePath = "runs/1/x.ome.tif";
        c.umPerPx = 8;
        c.stage = {1, 2, 3};
        c.exposureUs = 1000;
        return c;
    }
};

} // namespace

TEST_F(JournalTest, RunLifecycleAndPlanOrder) {
    auto j = Journal::open(file());
    ASSERT_TRUE(j) << j.error().message;
    auto id = (*j)->createRun("brain-1", {{"name", "brain-1"}}, {{"objective", "4x"}}, twoSlides());
    ASSERT_TRUE(id);
    auto run = (*j)->run(*id);
    ASSERT_TRUE(run);
    EXPECT_EQ(run->state, RunState::Queued);
    EXPECT_EQ(run->sectionCount, 6);
    EXPECT_EQ(run->settings["objective"], "4x");
    auto next = (*j)->nextRun();
    ASSERT_TRUE(next && *next);
    EXPECT_EQ((*next)->id, *id);

    ASSERT_TRUE((*j)->setRunState(*id, RunState::Running));
    EXPECT_FALSE((*j)->run(*id)->startedUtc.empty());
    // Sections come in plan order: slide by slide, section by section.
    std::vector<std::string> order;
    for (;;) {
        auto s = (*j)->nextSectionToCapture(*id);
        ASSERT_TRUE(s);
        if (!*s)
            break;
        order.push_back((*s)->slideName + "/" + (*s)->name);
        auto c = (*j)->recordCapture(captureOf((*s)->id));
        ASSERT_TRUE(c) << c.error().message;
        EXPECT_EQ((*j)->capture(*c)->attempt, 1);
    }
    EXPECT_EQ(order, (std::vector<std::string>{"slide-1/s1", "slide-1/s2", "slide-1/s3",
                                               "slide-2/s1", "slide-2/s2", "slide-2/s3"}));
    auto waiting = (*j)->capturesAwaitingRegistration();
    ASSERT_TRUE(waiting);
    ASSERT_EQ(waiting->size(), 6u);
    for (std::size_t k = 0; k < waiting->size(); ++k) {
        RegistrationRecord r;
        r.captureId = (*waiting)[k];
        r.atlasSlice = 10;
        r.damaged = k == 2;
        r.result = {{"damaged", r.damaged}};
        ASSERT_TRUE((*j)->recordRegistration(r));
    }
    EXPECT_TRUE((*j)->capturesAwaitingRegistration()->empty());
    EXPECT_EQ((*j)->run(*id)->doneCount, 6);
    auto secs = (*j)->sections(*id);
    EXPECT_EQ((*secs)[2].state, SectionState::Damaged);
    EXPECT_EQ((*secs)[1].state, SectionState::Registered);

    ASSERT_TRUE((*j)->setRunState(*id, RunState::Finished));
    EXPECT_FALSE((*j)->run(*id)->endedUtc.empty());
    auto again = (*j)->setRunState(*id, RunState::Running);
    ASSERT_FALSE(again);
    EXPECT_EQ(again.error().code, core::ErrorCode::InvalidArgument);
    EXPECT_TRUE((*j)->checkIntegrity());
}

TEST_F(JournalTest, RescanKeepsBothRecordsAndReopensAFinishedRun) {
    auto j = Journal::open(file());
    ASSERT_TRUE(j);
    auto id = (*j)->createRun("r", {}, {}, twoSlides());
    auto s = (*j)->nextSectionToCapture(*id);
    const std::int64_t sid = (*s)->id;
    // Not yet captured: nothing to rescan.
    auto early = (*j)->requestRescan(sid);
    ASSERT_FALSE(early);
    EXPECT_EQ(early.error().code, core::ErrorCode::InvalidArgument);
    auto c1 = (*j)->recordCapture(captureOf(sid));
    RegistrationRecord r;
    r.captureId = *c1;
    r.damaged = true;
    ASSERT_TRUE((*j)->recordRegistration(r));
    ASSERT_TRUE((*j)->setRunState(*id, RunState::Running));
    ASSERT_TRUE((*j)->setRunState(*id, RunState::Finished));

    ASSERT_TRUE((*j)->requestRescan(sid));
    EXPECT_EQ((*j)->section(sid)->state, SectionState::Rescan);
    EXPECT_EQ((*j)->run(*id)->state, RunState::Queued);
    auto next = (*j)->nextSectionToCapture(*id);
    ASSERT_TRUE(next && *next);
    EXPECT_EQ((*next)->id, sid);
    auto c2 = (*j)->recordCapture(captureOf(sid));
    ASSERT_TRUE(c2);
    EXPECT_EQ((*j)->capture(*c2)->attempt, 2);
    EXPECT_EQ((*j)->captures(sid)->size(), 2u);
    EXPECT_EQ((*j)->registrations(sid)->size(), 1u);
    // Capturing a section that is not waiting for one is refused.
    auto dup = (*j)->recordCapture(captureOf(sid));
    ASSERT_FALSE(dup);
    EXPECT_EQ(dup.error().code, core::ErrorCode::InvalidArgument);
}

TEST_F(JournalTest, AlertsStayOpenUntilAcknowledged) {
    auto j = Journal::open(file());
    ASSERT_TRUE(j);
    AlertRecord a;
    a.kind = AlertKind::Damaged;
    a.severity = AlertSeverity::Critical;
    a.message = "torn";
    auto id = (*j)->raiseAlert(a);
    ASSERT_TRUE(id);
    EXPECT_EQ((*j)->alerts(true)->size(), 1u);
    auto ack = (*j)->acknowledgeAlert(*id, "accept");
    ASSERT_TRUE(ack);
    EXPECT_TRUE(ack->acknowledgedUtc.has_value());
    EXPECT_EQ(ack->ackAction, "accept");
    EXPECT_TRUE((*j)->alerts(true)->empty());
    EXPECT_EQ((*j)->alerts(false)->size(), 1u);
    auto twice = (*j)->acknowledgeAlert(*id, "accept");
    ASSERT_FALSE(twice);
    EXPECT_EQ(twice.error().code, core::ErrorCode::InvalidArgument);
    auto none = (*j)->acknowledgeAlert(999, "accept");
    ASSERT_FALSE(none);
    EXPECT_EQ(none.error().code, core::ErrorCode::NotFound);
    // Typed as an enum, a bad severity cannot be raised; the schema's CHECK still refuses one
    // written beside the daemon.
    sqlite3* db = nullptr;
    ASSERT_EQ(sqlite3_open(file().c_str(), &db), SQLITE_OK);
    EXPECT_NE(sqlite3_exec(db,
                           "INSERT INTO alerts (kind, severity, message, raised_utc) VALUES "
                           "('damaged', 'whatever', 'm', '2024-01-01T00:00:00Z')",
                           nullptr, nullptr, nullptr),
              SQLITE_OK);
    sqlite3_close(db);
}

TEST_F(JournalTest, AnUnknownStoredAlertKindIsAnErrorNamingIt) {
    auto j = Journal::open(file());
    ASSERT_TRUE(j);
    AlertRecord a;
    a.kind = AlertKind::LowDisk;
    a.severity = AlertSeverity::Critical;
    auto id = (*j)->raiseAlert(a);
    ASSERT_TRUE(id);
    auto back = (*j)->alert(*id);
    ASSERT_TRUE(back);
    EXPECT_EQ(back->kind, AlertKind::LowDisk);
    EXPECT_EQ(back->severity, AlertSeverity::Critical);
    sqlite3* db = nullptr;
    ASSERT_EQ(sqlite3_open(file().c_str(), &db), SQLITE_OK);
    ASSERT_EQ(
        sqlite3_exec(db, "UPDATE alerts SET kind = 'meteor_strike'", nullptr, nullptr, nullptr),
        SQLITE_OK);
    sqlite3_close(db);
    auto one = (*j)->alert(*id);
    auto all = (*j)->alerts(false);
    ASSERT_FALSE(one);
    ASSERT_FALSE(all);
    for (const core::Error& e : {one.error(), all.error()}) {
        EXPECT_EQ(e.code, core::ErrorCode::IoError);
        EXPECT_NE(e.message.find("unknown alert kind \"meteor_strike\""), std::string::npos)
            << e.message;
    }
}

TEST_F(JournalTest, PersistsAcrossReopenAndMissingRecordsAreNotFound) {
    std::int64_t id = 0;
    {
        auto j = Journal::open(file());
        ASSERT_TRUE(j);
        id = *(*j)->createRun("persist", {}, {}, twoSlides());
        ASSERT_TRUE((*j)->setRunState(id, RunState::Running));
    }
    auto j = Journal::open(file());
    ASSERT_TRUE(j);
    EXPECT_EQ((*j)->run(id)->state, RunState::Running);
    // A running run (crash) is picked before queued ones.
    auto other = (*j)->createRun("later", {}, {}, twoSlides());
    ASSERT_TRUE(other);
    EXPECT_EQ((*(*j)->nextRun())->id, id);
    EXPECT_EQ((*j)->run(12345).error().code, core::ErrorCode::NotFound);
    EXPECT_EQ((*j)->section(12345).error().code, core::ErrorCode::NotFound);
    EXPECT_EQ((*j)->capture(12345).error().code, core::ErrorCode::NotFound);
    EXPECT_EQ((*j)->failSection(12345, "x").error().code, core::ErrorCode::NotFound);
    EXPECT_EQ((*j)->setRunState(12345, RunState::Paused).error().code, core::ErrorCode::NotFound);
    RegistrationRecord r;
    r.captureId = 12345;
    EXPECT_EQ((*j)->recordRegistration(r).error().code, core::ErrorCode::NotFound);
}

TEST_F(JournalTest, WalAndForeignKeysAreOn) {
    auto j = Journal::open(file());
    ASSERT_TRUE(j);
    sqlite3* db = nullptr;
    ASSERT_EQ(sqlite3_open(file().c_str(), &db), SQLITE_OK);
    sqlite3_stmt* st = nullptr;
    sqlite3_prepare_v2(db, "PRAGMA journal_mode", -1, &st, nullptr);
    ASSERT_EQ(sqlite3_step(st), SQLITE_ROW);
    EXPECT_STREQ(reinterpret_cast<const char*>(sqlite3_column_text(st, 0)), "wal");
    sqlite3_finalize(st);
    sqlite3_prepare_v2(db, "PRAGMA user_version", -1, &st, nullptr);
    ASSERT_EQ(sqlite3_step(st), SQLITE_ROW);
    EXPECT_EQ(sqlite3_column_int(st, 0), Journal::kSchemaVersion);
    sqlite3_finalize(st);
    sqlite3_close(db);
    // A capture for a section that does not exist is refused (foreign key / lookup).
    auto c = (*j)->recordCapture(captureOf(777));
    ASSERT_FALSE(c);
    EXPECT_EQ(c.error().code, core::ErrorCode::NotFound);
}

TEST_F(JournalTest, RefusesANewerSchemaAndAFileThatIsNotADatabase) {
    {
        sqlite3* db = nullptr;
        ASSERT_EQ(sqlite3_open(file().c_str(), &db), SQLITE_OK);
        sqlite3_exec(db, "PRAGMA user_version = 99", nullptr, nullptr, nullptr);
        sqlite3_close(db);
    }
    auto j = Journal::open(file());
    ASSERT_FALSE(j);
    EXPECT_EQ(j.error().code, core::ErrorCode::Unsupported);
    EXPECT_NE(j.error().message.find("99"), std::string::npos);

    const auto junk = dir_ / "junk.sqlite";
    std::ofstream(junk) << "this is not an SQLite file, it is a plan someone saved here\n";
    auto k = Journal::open(junk);
    ASSERT_FALSE(k);
    EXPECT_EQ(k.error().code, core::ErrorCode::IoError);
    EXPECT_NE(k.error().message.find("junk.sqlite"), std::string::npos);
    // Nothing of the user's file was overwritten.
    std::ifstream in(junk);
    std::string first;
    std::getline(in, first);
    EXPECT_EQ(first, "this is not an SQLite file, it is a plan someone saved here");

    auto m = Journal::open(dir_ / "no-such-dir" / "j.sqlite");
    ASSERT_FALSE(m);
    EXPECT_EQ(m.error().code, core::ErrorCode::IoError);
}

TEST_F(JournalTest, AFullDiskIsReportedAsEnospcAndNothingIsLost) {
    auto& vfs = testing_vfs::FullDiskVfs::install();
    auto j = Journal::open(file());
    ASSERT_TRUE(j);
    auto run = (*j)->createRun("r", {}, {}, twoSlides());
    ASSERT_TRUE(run) << run.error().message;
    auto secs = (*j)->sections(*run);
    ASSERT_TRUE(secs);
    AlertRecord a;
    a.kind = AlertKind::LowDisk;
    a.severity = AlertSeverity::Critical;
    a.message = "full";
    vfs.setFull(true);
    auto refused = (*j)->raiseAlert(a);
    auto refusedCapture = (*j)->recordCapture(captureOf((*secs)[0].id));
    auto refusedState = (*j)->setRunState(*run, RunState::Paused, "low_disk");
    vfs.setFull(false);
    ASSERT_FALSE(refused);
    EXPECT_EQ(refused.error().sysErrno, ENOSPC) << refused.error().message;
    ASSERT_FALSE(refusedCapture);
    EXPECT_EQ(refusedCapture.error().sysErrno, ENOSPC) << refusedCapture.error().message;
    ASSERT_FALSE(refusedState);
    EXPECT_EQ(refusedState.error().sysErrno, ENOSPC);
    // Nothing half-written; the same writes succeed once there is space.
    EXPECT_TRUE((*j)->alerts(false)->empty());
    EXPECT_TRUE((*j)->captures((*secs)[0].id)->empty());
    EXPECT_TRUE((*j)->checkIntegrity());
    ASSERT_TRUE((*j)->raiseAlert(a));
    auto c = (*j)->recordCapture(captureOf((*secs)[0].id));
    ASSERT_TRUE(c);
    ASSERT_TRUE((*j)->setRunState(*run, RunState::Paused, "low_disk"));
    // The capture that refers to an image is found by its path (the image writer asks it).
    auto owner = (*j)->captureWithImage("runs/1/x.ome.tif");
    ASSERT_TRUE(owner);
    EXPECT_EQ(*owner, std::optional<std::int64_t>(*c));
    EXPECT_EQ(*(*j)->captureWithImage("runs/1/y.ome.tif"), std::nullopt);
}
