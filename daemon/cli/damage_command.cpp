// slicectl damage report | threshold: the lab's damage report and the station's flag score,
// through the daemon's API (docs/damage.md, "The score, the threshold and the lab's report").
#include "slicestation/daemon/cli/cli.hpp"
#include "slicestation/daemon/cli/cli_output.hpp"
#include "slicestation/daemon/station/damage_report.hpp"

#include "daemon_client.hpp"

#include <cstdio>
#include <iostream>
#include <memory>

namespace slicestation::daemon {

using namespace client;

namespace {

struct DamageOpts {
    Connection c;
    std::string since;
    double rate = 0.05;
    bool apply = false;
    bool json = false;
    double score = 0.5;
};

struct DamageCommands {
    CLI::App *damage = nullptr, *report = nullptr, *threshold = nullptr, *set = nullptr,
             *clear = nullptr;
};

std::string score2(const nlohmann::json& v) {
    if (!v.is_number())
        return "unknown";
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.2f", v.get<double>());
    return buf;
}

std::string thresholdLine(const nlohmann::json& t) {
    return plainNumber(t.value("flag_score", 0.0)) + " (" + text(t, "source") +
           (t.value("source", "") == "set" ? " " + localTime(text(t, "set_utc")) : "") + ")";
}

void printReport(const nlohmann::json& j) {
    const int confirmed = j.value("confirmed", 0), fa = j.value("false_alarms", 0);
    std::vector<std::vector<std::string>> rows{
        {"since", text(j, "since").empty() ? "the first flag" : text(j, "since") + " (UTC)"},
        {"flags", text(j, "flags")},
        {"confirmed (rescan)", text(j, "confirmed")},
        {"false alarms (accept)", text(j, "false_alarms")},
        {"unanswered", text(j, "unanswered")},
        {"answered otherwise", text(j, "other_answers")},
        {"precision", j["precision"].is_number()
                          ? score2(j["precision"]) + " (" + std::to_string(confirmed) + " of " +
                                std::to_string(confirmed + fa) + " answered)"
                          : "none answered yet"}};
    const std::string rate = plainNumber(j.value("target_false_alarm_rate", 0.05));
    if (j["threshold"].is_number()) {
        const auto& at = j["at_threshold"];
        rows.push_back({"threshold for false alarms <= " + rate,
                        score2(j["threshold"]) + " (keeps " + text(at, "flags") +
                            " answered: " + text(at, "confirmed") + " confirmed, " +
                            text(at, "false_alarms") + " false alarms)"});
    } else {
        rows.push_back({"threshold for false alarms <= " + rate,
                        "none: no answered flag with a score, or the highest-scored one is a "
                        "false alarm"});
    }
    if (j["lowest_flag_score_applied"].is_number())
        rows.push_back({"lowest flag score applied",
                        score2(j["lowest_flag_score_applied"]) + " (no answers exist below it)"});
    if (j.contains("current"))
        rows.push_back({"flag score now", thresholdLine(j["current"])});
    const auto& cr = j["check_registration"];
    rows.push_back({"check_registration alerts", text(cr, "alerts") + " (" + text(cr, "rescanned") +
                                                     " rescanned, " + text(cr, "accepted") +
                                                     " accepted)"});
    std::cout << formatTable({"DAMAGE REPORT", ""}, rows);
    std::vector<std::vector<std::string>> open;
    for (const auto& f : j["unanswered_flags"])
        open.push_back({text(f, "alert_id"), text(f, "run_id"), text(f, "slide"),
                        text(f, "section"), score2(f["damage_score"]),
                        localTime(text(f, "raised_utc"))});
    if (!open.empty())
        std::cout << "\nunanswered flags (answer with slicectl alerts ack ALERT --action "
                     "rescan|accept):\n"
                  << formatTable({"ALERT", "RUN", "SLIDE", "SECTION", "SCORE", "RAISED"}, open)
                  << "(" << localZoneLabel() << ")\n";
}

std::string reportPath(const DamageOpts& o) {
    std::string path = "/api/damage/report?target_false_alarm_rate=" + plainNumber(o.rate);
    if (!o.since.empty())
        path += "&since=" + o.since; // parseSinceUtc passed: only [0-9T:.Z-]
    return path;
}

int run(const DamageOpts& o, const DamageCommands& c) {
    if (*c.report)
        if (auto since = parseSinceUtc(o.since); !since)
            return reportError("damage report", since.error());
    if (*c.report && !o.apply)
        return finish("damage report", request(o.c, "GET", reportPath(o)), o.json, printReport);
    if (*c.report) {
        auto r = request(o.c, "GET", reportPath(o));
        if (!r || r->status != 200)
            return finish("damage report", r, o.json);
        const auto j = nlohmann::json::parse(r->body, nullptr, false);
        if (j.is_discarded() || !j.contains("threshold"))
            return reportError("damage report",
                               core::makeError(core::ErrorCode::IoError,
                                               "the daemon's report is not the expected JSON"));
        if (!j["threshold"].is_number()) {
            if (!o.json)
                printReport(j);
            std::cerr << "slicectl damage report: error: --apply: no threshold keeps the "
                         "false-alarm rate at "
                      << plainNumber(o.rate) << " on this history; the flag score is unchanged\n";
            return kExitConflict;
        }
        const double t = j["threshold"].get<double>();
        return finish(
            "damage report --apply",
            request(o.c, "POST", "/api/damage/threshold", nlohmann::json{{"flag_score", t}}.dump()),
            o.json, [&](const nlohmann::json& now) {
                printReport(j);
                std::cout << "\nflag score set to " << thresholdLine(now)
                          << "; runs submitted from now on use it\n";
            });
    }
    if (*c.set)
        return finish("damage threshold set",
                      request(o.c, "POST", "/api/damage/threshold",
                              nlohmann::json{{"flag_score", o.score}}.dump()),
                      o.json, [](const nlohmann::json& now) {
                          std::cout << "flag score " << thresholdLine(now)
                                    << "; runs submitted from now on use it\n";
                      });
    if (*c.clear)
        return finish("damage threshold clear",
                      request(o.c, "POST", "/api/damage/threshold",
                              nlohmann::json{{"flag_score", nullptr}}.dump()),
                      o.json, [](const nlohmann::json& now) {
                          std::cout << "flag score " << thresholdLine(now)
                                    << "; runs submitted from now on use it\n";
                      });
    if (*c.threshold)
        return finish("damage threshold", request(o.c, "GET", "/api/damage/threshold"), o.json,
                      [](const nlohmann::json& now) {
                          std::cout << "flag score " << thresholdLine(now) << "\n";
                      });
    return -1;
}

} // namespace

CommandRunner addDamageCommands(CLI::App& app) {
    auto o = std::make_shared<DamageOpts>();
    DamageCommands c;
    c.damage = app.add_subcommand(
        "damage", "The lab's damage report and the station's flag score (docs/damage.md)");
    c.report = c.damage->add_subcommand(
        "report", "Measured precision of the damage flag from the technicians' answers, and the "
                  "flag score that would have kept false alarms at a target rate");
    c.report->add_option("--since", o->since, "Only flags raised from this UTC date (YYYY-MM-DD)");
    c.report
        ->add_option("--target-false-alarm-rate", o->rate,
                     "Highest share of false alarms among the flags kept (default 0.05)")
        ->check(finiteRange(0, 1));
    c.report->add_flag("--apply", o->apply,
                       "Tell the station to use the threshold found (needs the control token)");
    c.threshold = c.damage->add_subcommand(
        "threshold", "The flag score runs submitted now use (show, set or clear)");
    c.set = c.threshold->add_subcommand("set", "Use this flag score for the runs submitted from "
                                               "now on (kept in the journal)");
    c.set->add_option("SCORE", o->score, "Flag score in [0, 1]")
        ->required()
        ->check(finiteRange(0, 1));
    c.clear = c.threshold->add_subcommand(
        "clear", "Forget the score set; back to the station file's [damage] flag_score");
    c.damage->require_subcommand(1);
    for (auto* sub : {c.report, c.threshold, c.set, c.clear}) {
        addConnectionOptions(sub, o->c);
        sub->add_flag("--json", o->json,
                      "Print the daemon's JSON (for scripts) instead of a table");
    }
    return [o, c]() -> int { return run(*o, c); };
}

} // namespace slicestation::daemon
