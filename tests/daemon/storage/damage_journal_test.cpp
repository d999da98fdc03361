// Issue 18 in the journal: schema version 2 (score, verdict, flag score; station settings), the
// migration of a version-1 file, the damage flags with their answers, and the lab's report
// computed from them.
#include "../../common/journal_fixture.hpp"
#include "slicestation/daemon/config/config_document.hpp"
#include "slicestation/daemon/config/daemon_settings.hpp"
#include "slicestation/daemon/station/damage_report.hpp"
#include "slicestation/daemon/storage/journal.hpp"
#include "storage/shipped_schemas.hpp"

#include <gtest/gtest.h>
#include <sqlite3.h>

#include <cmath>
#include <filesystem>

using namespace slicestation;
using namespace slicestation::daemon;
using slicestation::testing_journal::kShippedVersion1;

namespace {

class DamageJournalTest : public testing_journal::JournalDirTest {
protected:
    DamageJournalTest() : JournalDirTest("damage-journal") {}

    static RegistrationRecord scored(std::int64_t captureId, double score, double flagScore,
                                     const std::string& verdict) {
        RegistrationRecord r;
        r.captureId = captureId;
        r.damageScore = score;
        r.flagScore = flagScore;
        r.damageVerdict = verdict;
        r.damaged = verdict == "damaged";
        return r;
    }
};

DamageFlag flag(double score, const std::string& action, bool answered = true,
                AlertKind kind = AlertKind::Damaged) {
    DamageFlag f;
    f.kind = kind;
    f.damageScore = score;
    f.flagScore = 0.5;
    if (answered)
        f.acknowledgedUtc = "2026-12-02T10:00:00.000Z";
    f.ackAction = action;
    return f;
}

} // namespace

TEST_F(DamageJournalTest, AVersion1FileMigratesAndItsOldRowsHaveNoScore) {
    {
        sqlite3* db = nullptr;
        ASSERT_EQ(sqlite3_open(file().c_str(), &db), SQLITE_OK);
        ASSERT_EQ(sqlite3_exec(db, kShippedVersion1, nullptr, nullptr, nullptr), SQLITE_OK);
        const char* rows =
            "PRAGMA user_version = 1;"
            "INSERT INTO runs VALUES (1,'old','finished','','{}','{}','2026-01-01T00:00:00.000Z',"
            "'','');"
            "INSERT INTO sections VALUES (1,1,0,'slide-1',0,'s1',0,0,0,0,NULL,'damaged','');"
            "INSERT INTO captures VALUES (1,1,1,'x.tif',8,0,0,0,NULL,1,1,1000,1,"
            "'2026-01-01T00:00:01.000Z');"
            "INSERT INTO registrations VALUES (1,1,10,NULL,1,0.2,'1 tear','',0.9,'r','o','l','{}',"
            "'2026-01-01T00:00:02.000Z');"
            "INSERT INTO alerts VALUES (1,1,1,'damaged','critical','s1 is damaged',"
            "'2026-01-01T00:00:03.000Z','2026-01-01T00:01:00.000Z','accept');";
        ASSERT_EQ(sqlite3_exec(db, rows, nullptr, nullptr, nullptr), SQLITE_OK)
            << sqlite3_errmsg(db);
        sqlite3_close(db);
    }
    auto j = Journal::open(file());
    ASSERT_TRUE(j) << j.error().message;
    auto regs = (*j)->registrations(1);
    ASSERT_TRUE(regs);
    ASSERT_EQ(regs->size(), 1u);
    EXPECT_TRUE((*regs)[0].damaged);
    EXPECT_FALSE((*regs)[0].damageScore.has_value()) << "unknown, not 0";
    EXPECT_EQ((*regs)[0].damageVerdict, "");
    EXPECT_FALSE((*regs)[0].flagScore.has_value());
    EXPECT_TRUE(toJson((*regs)[0])["damage_score"].is_null());
    auto sec = (*j)->section(1);
    ASSERT_TRUE(sec);
    EXPECT_FALSE(sec->damageScore.has_value());
    // The old flag and its answer count; its score is unknown.
    auto flags = (*j)->damageFlags("");
    ASSERT_TRUE(flags);
    ASSERT_EQ(flags->size(), 1u);
    EXPECT_EQ((*flags)[0].ackAction, "accept");
    EXPECT_FALSE((*flags)[0].damageScore.has_value());
    auto report = computeDamageReport(*flags, 0.05);
    ASSERT_TRUE(report);
    EXPECT_EQ(report->falseAlarms, 1);
    EXPECT_EQ(report->unknownScore, 1);
    EXPECT_FALSE(report->threshold.has_value());
    EXPECT_TRUE((*j)->checkIntegrity());
}

TEST_F(DamageJournalTest, ScoresVerdictsAndSettingsAreStoredAndBadOnesRefused) {
    auto j = Journal::open(file());
    ASSERT_TRUE(j);
    const auto ids = testing_journal::runWithCaptures(**j, 3).sectionIds;
    auto caps = [&](std::int64_t s) { return (*j)->captures(s)->back().id; };
    ASSERT_TRUE((*j)->recordRegistration(scored(caps(ids[0]), 0.83, 0.5, "damaged")));
    ASSERT_TRUE((*j)->recordRegistration(scored(caps(ids[1]), 0.62, 0.5, "check_registration")));
    auto s1 = (*j)->section(ids[0]);
    EXPECT_EQ(s1->state, SectionState::Damaged);
    EXPECT_DOUBLE_EQ(*s1->damageScore, 0.83);
    EXPECT_EQ(s1->damageVerdict, "damaged");
    auto s2 = (*j)->section(ids[1]);
    EXPECT_EQ(s2->state, SectionState::Registered) << "check_registration is not damaged";
    EXPECT_EQ(toJson(*s2)["damage_verdict"], "check_registration");
    // The journal refuses a verdict or a score it does not know (CHECK constraints).
    EXPECT_FALSE((*j)->recordRegistration(scored(caps(ids[2]), 0.5, 0.5, "torn")));
    EXPECT_FALSE((*j)->recordRegistration(scored(caps(ids[2]), 1.5, 0.5, "damaged")));

    auto none = (*j)->setting("damage.flag_score");
    ASSERT_TRUE(none);
    EXPECT_FALSE(none->has_value());
    ASSERT_TRUE((*j)->setSetting("damage.flag_score", 0.7));
    ASSERT_TRUE((*j)->setSetting("damage.flag_score", 0.74));
    auto set = (*j)->setting("damage.flag_score");
    ASSERT_TRUE(set && set->has_value());
    EXPECT_DOUBLE_EQ((*set)->value.get<double>(), 0.74);
    EXPECT_FALSE((*set)->setUtc.empty());
    ASSERT_TRUE((*j)->clearSetting("damage.flag_score"));
    EXPECT_FALSE((*j)->setting("damage.flag_score")->has_value());
}

TEST_F(DamageJournalTest, AFlagCarriesTheScoreOfTheRegistrationItWasRaisedFor) {
    auto j = Journal::open(file());
    ASSERT_TRUE(j);
    const auto ids = testing_journal::runWithCaptures(**j, 1).sectionIds;
    const auto cap1 = (*j)->captures(ids[0])->back().id;
    auto r1 = scored(cap1, 0.9, 0.5, "damaged");
    r1.registeredUtc = "2026-12-02T10:00:00.000Z";
    ASSERT_TRUE((*j)->recordRegistration(r1));
    AlertRecord a;
    a.sectionId = ids[0];
    a.kind = AlertKind::Damaged;
    a.severity = AlertSeverity::Critical;
    a.raisedUtc = "2026-12-02T10:00:00.001Z";
    auto first = (*j)->raiseAlert(a);
    ASSERT_TRUE(first);
    ASSERT_TRUE((*j)->acknowledgeAlert(*first, "rescan"));
    ASSERT_TRUE((*j)->requestRescan(ids[0]));
    CaptureRecord c;
    c.sectionId = ids[0];
    c.imagePath = "y.tif";
    c.umPerPx = 8;
    auto cap2 = (*j)->recordCapture(c);
    ASSERT_TRUE(cap2);
    auto r2 = scored(*cap2, 0.55, 0.5, "damaged");
    r2.registeredUtc = "2026-12-02T11:00:00.000Z";
    ASSERT_TRUE((*j)->recordRegistration(r2));
    a.raisedUtc = "2026-12-02T11:00:00.002Z";
    ASSERT_TRUE((*j)->raiseAlert(a));
    a.kind = AlertKind::AtlasMismatch; // not a damage alert: not listed
    ASSERT_TRUE((*j)->raiseAlert(a));

    auto flags = (*j)->damageFlags("");
    ASSERT_TRUE(flags);
    ASSERT_EQ(flags->size(), 2u);
    EXPECT_DOUBLE_EQ(*(*flags)[0].damageScore, 0.9);
    EXPECT_EQ((*flags)[0].ackAction, "rescan");
    EXPECT_DOUBLE_EQ(*(*flags)[1].damageScore, 0.55);
    EXPECT_FALSE((*flags)[1].acknowledgedUtc.has_value());
    EXPECT_EQ((*flags)[1].sectionName, "s1");
    // since: a prefix of the UTC time, compared as text.
    EXPECT_EQ((*j)->damageFlags("2026-12-02T10:30")->size(), 1u);
    EXPECT_EQ((*j)->damageFlags("2026-12-03")->size(), 0u);
}

TEST(DamageReport, CountsAnswersAndSweepsTheThreshold) {
    // Answered: confirmed at 0.95, 0.90, 0.70, 0.60; false alarms at 0.80, 0.55, 0.52.
    std::vector<DamageFlag> flags = {flag(0.95, "rescan"),
                                     flag(0.80, "accept"),
                                     flag(0.90, "rescan"),
                                     flag(0.70, "rescan"),
                                     flag(0.55, "accept"),
                                     flag(0.60, "rescan"),
                                     flag(0.52, "accept"),
                                     flag(0.99, "", false),
                                     flag(0.75, "re-mounted by hand"),
                                     flag(0.65, "accept", true, AlertKind::CheckRegistration)};
    auto r = computeDamageReport(flags, 0.05);
    ASSERT_TRUE(r);
    EXPECT_EQ(r->flags, 9);
    EXPECT_EQ(r->confirmed, 4);
    EXPECT_EQ(r->falseAlarms, 3);
    EXPECT_EQ(r->unanswered, 1);
    EXPECT_EQ(r->otherAnswers, 1);
    EXPECT_EQ(r->checkRegistration, 1);
    EXPECT_EQ(r->checkRegistrationAccepted, 1);
    EXPECT_DOUBLE_EQ(*r->precision, 4.0 / 7.0);
    // By hand, rate 0.05: at 0.90 kept {0.95, 0.90}: 0 of 2; at 0.80 1 of 3 > 0.05. -> 0.90.
    EXPECT_DOUBLE_EQ(*r->threshold, 0.90);
    EXPECT_EQ(r->flagsAtThreshold, 2);
    EXPECT_EQ(r->falseAlarmsAtThreshold, 0);
    // Rate 0.25: at 0.70: {0.95, 0.90, 0.80, 0.70} 1 of 4 = 0.25 <= 0.25; at 0.60: 1 of 5 = 0.2
    // <= 0.25; at 0.55: 2 of 6 > 0.25. -> 0.60 (the lowest that holds).
    auto q = computeDamageReport(flags, 0.25);
    EXPECT_DOUBLE_EQ(*q->threshold, 0.60);
    EXPECT_EQ(q->flagsAtThreshold, 5);
    EXPECT_EQ(q->confirmedAtThreshold, 4);
    // Rate 0.5: everything answered may stay (3 of 7 <= 0.5): the lowest answered score.
    EXPECT_DOUBLE_EQ(*computeDamageReport(flags, 0.5)->threshold, 0.52);
    // The highest-scored answered flag a false alarm: no threshold keeps the rate at 0.
    auto none = computeDamageReport({flag(0.9, "accept"), flag(0.7, "rescan")}, 0.0);
    EXPECT_FALSE(none->threshold.has_value());
    EXPECT_DOUBLE_EQ(*none->precision, 0.5);
    // Nothing answered: no precision, no threshold.
    auto empty = computeDamageReport({flag(0.9, "", false)}, 0.05);
    EXPECT_FALSE(empty->precision.has_value());
    EXPECT_FALSE(empty->threshold.has_value());
    EXPECT_EQ(computeDamageReport(flags, 1.5).error().code, core::ErrorCode::InvalidArgument);
    EXPECT_FALSE(computeDamageReport(flags, std::nan("")));
    const auto j = toJson(*r);
    EXPECT_EQ(j["unanswered_flags"].size(), 1u);
    EXPECT_EQ(j["answered_flags"].size(), 7u);
}

TEST(DamageReport, SinceIsAUtcDateOrTimePrefix) {
    EXPECT_EQ(*parseSinceUtc(""), "");
    EXPECT_EQ(*parseSinceUtc("2026-12-01"), "2026-12-01");
    EXPECT_EQ(*parseSinceUtc("2026-12-01T08:30:00Z"), "2026-12-01T08:30:00");
    EXPECT_EQ(*parseSinceUtc("2026-12-01T08"), "2026-12-01T08");
    for (const char* bad : {"yesterday", "2026-13-01", "2026-12-1", "2026-12-01T", "2026/12/01",
                            "2026-12-01&x=1", "2026-12-01T08:30:00.0000"})
        EXPECT_FALSE(parseSinceUtc(bad)) << bad;
}

TEST(DamageSettings, FlagScoreIsReadCheckedAndSnapshotted) {
    const auto parse = [](const std::string& extra) {
        auto doc =
            parseDocument("[scan]\num_per_px = 2\n" + extra, DocumentFormat::Toml, "station.toml");
        EXPECT_TRUE(doc);
        return parseDaemonSettings(*doc, "station.toml");
    };
    auto plain = parse("");
    ASSERT_TRUE(plain);
    EXPECT_DOUBLE_EQ(plain->scan.damageFlagScore, 0.5);
    auto set = parse("[damage]\nflag_score = 0.74\n");
    ASSERT_TRUE(set) << set.error().message;
    EXPECT_DOUBLE_EQ(set->scan.damageFlagScore, 0.74);
    // The run's snapshot keeps it; an older snapshot without it reads the old decision line.
    const nlohmann::json snap = toJson(set->scan);
    EXPECT_DOUBLE_EQ(snap["damage_flag_score"].get<double>(), 0.74);
    EXPECT_DOUBLE_EQ(scanSettingsFromJson(snap, "run 1")->damageFlagScore, 0.74);
    nlohmann::json old = snap;
    old.erase("damage_flag_score");
    EXPECT_DOUBLE_EQ(scanSettingsFromJson(old, "run 1")->damageFlagScore, 0.5);
    // Out of range, not a number, or a key it does not know: refused, naming the key.
    for (const char* bad : {"[damage]\nflag_score = 1.5\n", "[damage]\nflag_score = \"high\"\n",
                            "[damage]\nflag_scor = 0.5\n", "damage = 3\n"}) {
        auto r = parse(bad);
        ASSERT_FALSE(r) << bad;
        EXPECT_NE(r.error().message.find("damage"), std::string::npos) << r.error().message;
    }
}
