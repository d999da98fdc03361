#include "slicestation/daemon/station/damage_report.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <set>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using core::Result;

Result<DamageReport> computeDamageReport(const std::vector<DamageFlag>& flags,
                                         double targetFalseAlarmRate) {
    if (!(targetFalseAlarmRate >= 0 && targetFalseAlarmRate <= 1))
        return makeError(ErrorCode::InvalidArgument,
                         "target false-alarm rate: expected a number in [0, 1]");
    DamageReport r;
    r.targetFalseAlarmRate = targetFalseAlarmRate;
    for (const DamageFlag& f : flags) {
        const bool open = !f.acknowledgedUtc.has_value();
        if (f.kind == AlertKind::CheckRegistration) {
            ++r.checkRegistration;
            r.checkRegistrationRescanned += !open && f.ackAction == "rescan";
            r.checkRegistrationAccepted += !open && f.ackAction == "accept";
            continue;
        }
        if (f.kind != AlertKind::Damaged)
            continue;
        ++r.flags;
        if (f.flagScore)
            r.lowestFlagScoreApplied =
                std::min(r.lowestFlagScoreApplied.value_or(1.0), *f.flagScore);
        if (open) {
            ++r.unanswered;
            r.unansweredFlags.push_back(f);
        } else if (f.ackAction == "rescan" || f.ackAction == "accept") {
            (f.ackAction == "rescan" ? r.confirmed : r.falseAlarms)++;
            r.answeredFlags.push_back(f);
            r.unknownScore += !f.damageScore.has_value();
        } else {
            ++r.otherAnswers;
        }
    }
    if (r.confirmed + r.falseAlarms > 0)
        r.precision = static_cast<double>(r.confirmed) / (r.confirmed + r.falseAlarms);

    // The sweep: every stored score of an answered flag is a candidate, lowest first.
    std::set<double> candidates;
    for (const DamageFlag& f : r.answeredFlags)
        if (f.damageScore)
            candidates.insert(*f.damageScore);
    for (const double s : candidates) {
        int n = 0, fa = 0;
        for (const DamageFlag& f : r.answeredFlags)
            if (f.damageScore && *f.damageScore >= s) {
                ++n;
                fa += f.ackAction == "accept";
            }
        // fa / n <= R, without dividing (n > 0: s is the score of one of them).
        if (static_cast<double>(fa) <= targetFalseAlarmRate * n) {
            r.threshold = s;
            r.flagsAtThreshold = n;
            r.falseAlarmsAtThreshold = fa;
            r.confirmedAtThreshold = n - fa;
            break;
        }
    }
    return r;
}

Result<std::string> parseSinceUtc(const std::string& since) {
    if (since.empty())
        return since;
    std::string s = since;
    if (s.back() == 'Z')
        s.pop_back();
    // YYYY-MM-DD[THH[:MM[:SS[.fff]]]]: digits where the pattern has 9, the separators as given.
    static const std::string pattern = "9999-99-99T99:99:99.999";
    bool ok = s.size() >= 10 && s.size() <= pattern.size();
    for (std::size_t i = 0; ok && i < s.size(); ++i)
        ok = pattern[i] == '9' ? std::isdigit(static_cast<unsigned char>(s[i])) != 0
                               : s[i] == pattern[i];
    // A value may not end on a separator (2026-12-01T).
    ok = ok && std::isdigit(static_cast<unsigned char>(s.back())) != 0;
    if (ok) {
        const int month = std::stoi(s.substr(5, 2)), day = std::stoi(s.substr(8, 2));
        ok = month >= 1 && month <= 12 && day >= 1 && day <= 31;
    }
    if (!ok)
        return makeError(ErrorCode::InvalidArgument,
                         "since: expected a UTC date YYYY-MM-DD (optionally THH:MM:SS), got \"" +
                             since.substr(0, 40) + "\"");
    return s;
}

namespace {

nlohmann::json flagJson(const DamageFlag& f) {
    nlohmann::json j{{"alert_id", f.alertId},    {"section_id", f.sectionId},
                     {"section", f.sectionName}, {"slide", f.slideName},
                     {"kind", toString(f.kind)}, {"raised_utc", f.raisedUtc},
                     {"ack_action", f.ackAction}};
    j["run_id"] = f.runId ? nlohmann::json(*f.runId) : nlohmann::json();
    j["damage_score"] = f.damageScore ? nlohmann::json(*f.damageScore) : nlohmann::json();
    j["flag_score"] = f.flagScore ? nlohmann::json(*f.flagScore) : nlohmann::json();
    j["acknowledged_utc"] =
        f.acknowledgedUtc ? nlohmann::json(*f.acknowledgedUtc) : nlohmann::json();
    return j;
}

nlohmann::json opt(const std::optional<double>& v) {
    return v ? nlohmann::json(*v) : nlohmann::json();
}

} // namespace

nlohmann::json toJson(const DamageReport& r) {
    nlohmann::json j{{"target_false_alarm_rate", r.targetFalseAlarmRate},
                     {"flags", r.flags},
                     {"confirmed", r.confirmed},
                     {"false_alarms", r.falseAlarms},
                     {"answered", r.confirmed + r.falseAlarms},
                     {"unanswered", r.unanswered},
                     {"other_answers", r.otherAnswers},
                     {"unknown_score", r.unknownScore},
                     {"precision", opt(r.precision)},
                     {"threshold", opt(r.threshold)},
                     {"at_threshold",
                      {{"flags", r.flagsAtThreshold},
                       {"confirmed", r.confirmedAtThreshold},
                       {"false_alarms", r.falseAlarmsAtThreshold}}},
                     {"lowest_flag_score_applied", opt(r.lowestFlagScoreApplied)},
                     {"check_registration",
                      {{"alerts", r.checkRegistration},
                       {"rescanned", r.checkRegistrationRescanned},
                       {"accepted", r.checkRegistrationAccepted}}}};
    j["unanswered_flags"] = nlohmann::json::array();
    for (const auto& f : r.unansweredFlags)
        j["unanswered_flags"].push_back(flagJson(f));
    j["answered_flags"] = nlohmann::json::array();
    for (const auto& f : r.answeredFlags)
        j["answered_flags"].push_back(flagJson(f));
    return j;
}

} // namespace slicestation::daemon
