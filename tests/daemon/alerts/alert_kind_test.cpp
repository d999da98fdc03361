// The alert vocabulary: every kind and severity round-trips through its stored text, the texts
// are the ones the journal, the JSON API and the channels always carried, and unknown text is an
// error naming it (never taken for another kind or for "critical").
#include "slicestation/daemon/storage/alert_kind.hpp"

#include <gtest/gtest.h>

#include <set>
#include <string>

using namespace slicestation::daemon;

TEST(AlertKind, EveryKindRoundTripsThroughItsText) {
    std::set<std::string> texts;
    for (AlertKind k : kAlertKinds) {
        auto back = parseAlertKind(toString(k));
        ASSERT_TRUE(back) << toString(k);
        EXPECT_EQ(*back, k);
        texts.insert(toString(k));
    }
    EXPECT_EQ(texts.size(), std::size(kAlertKinds)) << "two kinds share a text";
}

TEST(AlertKind, TextsAreTheStoredOnes) {
    // The strings older journals and web pages hold: changing one breaks compatibility.
    const std::set<std::string> stored{
        "damaged", "atlas_mismatch", "registration_failed", "stage_fault", "camera_fault",
        "focus_fault", "storage_fault", "low_disk", "journal_error", "run_finished", "run_paused",
        "run_failed", "run_cancelled", "restarted", "alert_summary",
        // Added by journal schema version 2 (issue 18).
        "check_registration"};
    std::set<std::string> texts;
    for (AlertKind k : kAlertKinds)
        texts.insert(toString(k));
    EXPECT_EQ(texts, stored);
    EXPECT_STREQ(toString(AlertSeverity::Info), "info");
    EXPECT_STREQ(toString(AlertSeverity::Warning), "warning");
    EXPECT_STREQ(toString(AlertSeverity::Critical), "critical");
}

TEST(AlertKind, UnknownTextIsAnErrorNamingIt) {
    auto k = parseAlertKind("Damaged");
    ASSERT_FALSE(k);
    EXPECT_EQ(k.error().code, slicestation::core::ErrorCode::InvalidArgument);
    EXPECT_NE(k.error().message.find("\"Damaged\""), std::string::npos) << k.error().message;
    EXPECT_NE(k.error().message.find("low_disk"), std::string::npos) << "lists the known kinds";
    for (const char* bad : {"urgent", "", "CRITICAL", "critical "}) {
        auto s = parseAlertSeverity(bad);
        ASSERT_FALSE(s) << bad;
        EXPECT_EQ(s.error().code, slicestation::core::ErrorCode::InvalidArgument);
        EXPECT_NE(s.error().message.find(std::string("\"") + bad + "\""), std::string::npos);
        EXPECT_NE(s.error().message.find("info, warning, critical"), std::string::npos);
    }
}

TEST(AlertSeverity, OrderIsRankAndPriorityFollowsIt) {
    EXPECT_LT(AlertSeverity::Info, AlertSeverity::Warning);
    EXPECT_LT(AlertSeverity::Warning, AlertSeverity::Critical);
    EXPECT_EQ(syslogPriority(AlertSeverity::Info), 5);
    EXPECT_EQ(syslogPriority(AlertSeverity::Warning), 4);
    EXPECT_EQ(syslogPriority(AlertSeverity::Critical), 2);
    for (AlertSeverity s : kAlertSeverities)
        EXPECT_EQ(*parseAlertSeverity(toString(s)), s);
}
