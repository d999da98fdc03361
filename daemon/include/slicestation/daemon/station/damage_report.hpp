#pragma once
/// The lab's own damage report (issue 18; docs/damage.md, "The score, the threshold and the
/// lab's report"): from the journal's damage flags and the technicians' answers, the measured
/// precision of the flag and the threshold that would have kept the false-alarm rate at a target.
///
/// Definitions (every figure is a count over the flags given, nothing estimated):
/// - a flag is an alert of kind "damaged" on a section (one per flagged registration: a section
///   flagged again after a rescan is a second flag);
/// - answered "rescan" = damage confirmed; answered "accept" = false alarm; open = unanswered;
///   acknowledged with any other text = answered otherwise (counted, not used);
/// - precision = confirmed / (confirmed + false alarms);
/// - the threshold for a target rate R is the lowest stored score s of an answered flag such that
///   among the answered flags with score >= s, false alarms / flags <= R. Raising the flag score
///   to s would have kept exactly those flags on this history (any value above the next lower
///   answered score gives the same set). Only flags with a stored score take part (registrations
///   journalled before schema version 2 have none: counted as unknown_score).
/// - check_registration alerts are not damage flags: counted apart, with their answers.
#include "slicestation/core/result.hpp"
#include "slicestation/daemon/storage/journal.hpp"

#include <nlohmann/json.hpp>

#include <optional>
#include <string>
#include <vector>

namespace slicestation::daemon {

struct DamageReport {
    double targetFalseAlarmRate = 0.05;
    int flags = 0;        ///< alerts of kind damaged
    int confirmed = 0;    ///< answered "rescan"
    int falseAlarms = 0;  ///< answered "accept"
    int unanswered = 0;   ///< still open
    int otherAnswers = 0; ///< acknowledged with another text
    int unknownScore = 0; ///< answered flags without a stored score (before schema version 2)
    std::optional<double> precision; ///< confirmed / (confirmed + falseAlarms); none unanswered
    /// The lowest answered score keeping the false-alarm rate at the target (see above); none
    /// when no answered flag has a score, or not even the highest-scored answered flag alone
    /// keeps it (it is a false alarm).
    std::optional<double> threshold;
    int flagsAtThreshold = 0, confirmedAtThreshold = 0, falseAlarmsAtThreshold = 0;
    /// The lowest flag score the station applied to these flags: no answer exists below it, so
    /// the report can never propose a lower threshold.
    std::optional<double> lowestFlagScoreApplied;
    int checkRegistration = 0, checkRegistrationRescanned = 0, checkRegistrationAccepted = 0;
    std::vector<DamageFlag> unansweredFlags; ///< open damage flags, oldest first
    std::vector<DamageFlag> answeredFlags;   ///< rescan or accept, oldest first
};

/// The report over `flags` (Journal::damageFlags). InvalidArgument when the rate is not in
/// [0, 1].
[[nodiscard]] core::Result<DamageReport> computeDamageReport(const std::vector<DamageFlag>& flags,
                                                             double targetFalseAlarmRate);

/// "" for "", else `since` as an ISO 8601 UTC prefix the journal's times compare with as text
/// (YYYY-MM-DD, optionally THH, :MM, :SS, .mmm, a trailing Z dropped). InvalidArgument naming
/// the value otherwise.
[[nodiscard]] core::Result<std::string> parseSinceUtc(const std::string& since);

nlohmann::json toJson(const DamageReport& r);

} // namespace slicestation::daemon
