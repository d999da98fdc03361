// Issue 18, end to end through the daemon: a simulated run with every section flagged, the
// technicians' answers given through the HTTP API, the lab's damage report checked against what
// was answered and against the stored scores, the threshold applied through the API (and by
// slicectl), kept over a restart, and the next run's snapshot and verdicts using it.
#include "station_fixture.hpp"

#include <httplib.h>

#include <cstdio>
#include <sys/wait.h>

using namespace slicestation;
using namespace slicestation::daemon;
using namespace slicestation::testing_station;

namespace {

/// Runs a command line; its stdout and exit code.
std::pair<std::string, int> runCommand(const std::string& cmd) {
    std::string out;
    FILE* p = ::popen((cmd + " 2>/dev/null").c_str(), "r");
    if (!p)
        return {"", -1};
    char buf[4096];
    std::size_t n;
    while ((n = std::fread(buf, 1, sizeof buf, p)) > 0)
        out.append(buf, n);
    const int status = ::pclose(p);
    return {out, WIFEXITED(status) ? WEXITSTATUS(status) : -1};
}

class DamageReportTest : public StationTest {
protected:
    void startApi() {
        auto api = HttpApi::start(*rig_.station, "127.0.0.1", 0, kToken);
        ASSERT_TRUE(api) << api.error().message;
        rig_.api = std::move(*api);
    }
    void restart() {
        rig_.api->stop();
        rig_.api.reset();
        rig_.station->stop();
        rig_.station.reset();
        build(); // the same state directory, journal and all; the station file's flag score 0.5
        ASSERT_TRUE(rig_.station);
        startApi();
        rig_.station->start();
    }
    /// The damage score of the latest registration of each section of `run`, by name.
    std::map<std::string, RegistrationRecord> latestRegistrations(std::int64_t run) {
        std::map<std::string, RegistrationRecord> out;
        auto secs = rig_.station->journal().sections(run);
        EXPECT_TRUE(secs);
        for (const auto& s : *secs) {
            auto regs = rig_.station->journal().registrations(s.id);
            EXPECT_TRUE(regs && !regs->empty()) << s.name;
            if (regs && !regs->empty())
                out[s.name] = regs->back();
        }
        return out;
    }
};

} // namespace

TEST_F(DamageReportTest, AnswersThroughTheApiMakeTheReportAndItsThresholdIsAppliedToTheNextRun) {
    // A station that flags every section (flag_score 0): four flags for the technicians.
    build("[damage]\nflag_score = 0.0\n");
    startApi();
    httplib::Client cli("127.0.0.1", rig_.api->port());
    const httplib::Headers auth{{"Authorization", std::string("Bearer ") + kToken}};
    auto id = rig_.station->submitPlan(planFor({0, 1, 2, 3}), "plan");
    ASSERT_TRUE(id) << id.error().message;
    rig_.station->start();
    const RunRecord run1 = waitRun(*id, RunState::Finished);
    EXPECT_DOUBLE_EQ(run1.settings.value("damage_flag_score", -1.0), 0.0);

    // Every registration keeps its score, the verdict and the flag score applied.
    auto regs1 = latestRegistrations(*id);
    ASSERT_EQ(regs1.size(), 4u);
    for (const auto& [name, r] : regs1) {
        SCOPED_TRACE(name);
        ASSERT_TRUE(r.damageScore.has_value());
        EXPECT_GE(*r.damageScore, 0.0);
        EXPECT_LE(*r.damageScore, 1.0);
        EXPECT_EQ(r.damageVerdict, "damaged");
        EXPECT_EQ(r.flagScore, 0.0);
        EXPECT_TRUE(r.damaged);
        std::printf("run 1: %s damage_score %.4f\n", name.c_str(), *r.damageScore);
    }
    // The torn section (s3) scores above every clean one: what the threshold below relies on.
    for (const char* clean : {"s1", "s2", "s4"})
        EXPECT_GT(*regs1["s3"].damageScore, *regs1[clean].damageScore) << clean;
    // The sections API shows verdict and score.
    auto secsReply = cli.Get("/api/runs/" + std::to_string(*id) + "/sections");
    ASSERT_TRUE(secsReply);
    for (const auto& s : nlohmann::json::parse(secsReply->body)) {
        EXPECT_EQ(s["damage_verdict"], "damaged");
        EXPECT_DOUBLE_EQ(s["damage_score"].get<double>(),
                         *regs1[s["name"].get<std::string>()].damageScore);
    }

    // The alerts carry the score; the technicians answer through the API: s3 re-mounted
    // (rescan = damage confirmed), s1 and s2 accepted (false alarms), s4 left unanswered.
    auto damaged = alertsOf("damaged");
    ASSERT_EQ(damaged.size(), 4u);
    std::map<std::string, std::int64_t> alertOf;
    for (const auto& a : damaged) {
        auto s = rig_.station->journal().section(*a.sectionId);
        ASSERT_TRUE(s);
        alertOf[s->name] = a.id;
        char score[32];
        std::snprintf(score, sizeof score, "damaged, score %.2f", *regs1[s->name].damageScore);
        EXPECT_NE(a.message.find(score), std::string::npos) << a.message;
        EXPECT_EQ(a.severity, AlertSeverity::Critical);
    }
    const auto ack = [&](const std::string& name, const std::string& action) {
        auto r = cli.Post("/api/alerts/" + std::to_string(alertOf[name]) + "/ack", auth,
                          nlohmann::json{{"action", action}}.dump(), "application/json");
        ASSERT_TRUE(r);
        EXPECT_EQ(r->status, 200) << r->body;
    };
    ack("s3", "rescan");
    ack("s1", "accept");
    ack("s2", "accept");
    // The rescan captures s3 again; still torn in the simulation, it is flagged again: a fifth,
    // unanswered flag.
    waitRun(*id, RunState::Finished);
    ASSERT_EQ(alertsOf("damaged").size(), 5u);

    // The report, through the API, against what was answered.
    auto rep = cli.Get("/api/damage/report?target_false_alarm_rate=0.05");
    ASSERT_TRUE(rep);
    ASSERT_EQ(rep->status, 200) << rep->body;
    const auto report = nlohmann::json::parse(rep->body);
    std::printf("report: %s\n", report.dump().c_str());
    EXPECT_EQ(report["flags"], 5);
    EXPECT_EQ(report["confirmed"], 1);
    EXPECT_EQ(report["false_alarms"], 2);
    EXPECT_EQ(report["unanswered"], 2);
    EXPECT_EQ(report["other_answers"], 0);
    EXPECT_DOUBLE_EQ(report["precision"].get<double>(), 1.0 / 3.0);
    EXPECT_DOUBLE_EQ(report["lowest_flag_score_applied"].get<double>(), 0.0);
    // Each answered flag carries the score of the registration it was raised for.
    ASSERT_EQ(report["answered_flags"].size(), 3u);
    for (const auto& f : report["answered_flags"])
        EXPECT_DOUBLE_EQ(f["damage_score"].get<double>(),
                         *regs1[f["section"].get<std::string>()].damageScore);
    // By hand from the stored scores: at the torn section's score only it is kept (0 false
    // alarms of 1 <= 0.05); at any lower answered score a false alarm joins (>= 1 of 2 > 0.05).
    const double expected = *regs1["s3"].damageScore;
    ASSERT_TRUE(report["threshold"].is_number());
    EXPECT_DOUBLE_EQ(report["threshold"].get<double>(), expected);
    EXPECT_EQ(report["at_threshold"]["flags"], 1);
    EXPECT_EQ(report["at_threshold"]["confirmed"], 1);
    EXPECT_EQ(report["at_threshold"]["false_alarms"], 0);
    // At a tolerated rate of 1 every answered flag may stay: the lowest answered score.
    auto all = cli.Get("/api/damage/report?target_false_alarm_rate=1");
    const double lowestAnswered = std::min(*regs1["s1"].damageScore, *regs1["s2"].damageScore);
    EXPECT_DOUBLE_EQ(nlohmann::json::parse(all->body)["threshold"].get<double>(), lowestAnswered);
    // --since: nothing after tomorrow; a bad date is the request's fault.
    auto later = cli.Get("/api/damage/report?since=2999-01-01");
    EXPECT_EQ(nlohmann::json::parse(later->body)["flags"], 0);
    EXPECT_EQ(cli.Get("/api/damage/report?since=yesterday")->status, 400);
    EXPECT_EQ(cli.Get("/api/damage/report?target_false_alarm_rate=2")->status, 400);

    // slicectl prints the same report, and --apply tells the station to use the threshold.
    const std::string url = " --url http://127.0.0.1:" + std::to_string(rig_.api->port());
    auto [text, code] = runCommand(std::string(SLICECTL_PATH) + " damage report" + url);
    EXPECT_EQ(code, 0) << text;
    EXPECT_NE(text.find("0.33 (1 of 3 answered)"), std::string::npos) << text;
    std::printf("slicectl damage report:\n%s", text.c_str());
    auto [refused, refusedCode] =
        runCommand(std::string(SLICECTL_PATH) + " damage report --apply --token nope" + url);
    EXPECT_EQ(refusedCode, 3) << refused; // 401: the daemon refused
    auto [applied, appliedCode] = runCommand(
        std::string(SLICECTL_PATH) + " damage report --apply --json --token " + kToken + url);
    EXPECT_EQ(appliedCode, 0) << applied;
    auto th = cli.Get("/api/damage/threshold");
    const auto threshold = nlohmann::json::parse(th->body);
    EXPECT_DOUBLE_EQ(threshold["flag_score"].get<double>(), expected);
    EXPECT_EQ(threshold["source"], "set");
    // The API refuses a bad value and a request without the token.
    EXPECT_EQ(
        cli.Post("/api/damage/threshold", R"({"flag_score": 1.5})", "application/json")->status,
        401);
    EXPECT_EQ(cli.Post("/api/damage/threshold", auth, R"({"flag_score": 1.5})", "application/json")
                  ->status,
              400);
    EXPECT_EQ(
        cli.Post("/api/damage/threshold", auth, R"({"score": 0.5})", "application/json")->status,
        400);

    // It survives a restart (kept in the journal; the station file still says 0.5).
    restart();
    httplib::Client cli2("127.0.0.1", rig_.api->port());
    EXPECT_DOUBLE_EQ(
        nlohmann::json::parse(cli2.Get("/api/damage/threshold")->body)["flag_score"].get<double>(),
        expected);

    // The next run snapshots it, and the station flags from it.
    // (Two sections, to keep the test short: a former false alarm and the torn one.)
    auto id2 = rig_.station->submitPlan(planFor({0, 2}, "second"), "plan");
    ASSERT_TRUE(id2) << id2.error().message;
    const RunRecord run2 = waitRun(*id2, RunState::Finished);
    EXPECT_DOUBLE_EQ(run2.settings.value("damage_flag_score", -1.0), expected);
    auto regs2 = latestRegistrations(*id2);
    ASSERT_EQ(regs2.size(), 2u);
    for (const auto& [name, r] : regs2) {
        SCOPED_TRACE(name);
        std::printf("run 2: %s damage_score %.4f verdict %s\n", name.c_str(),
                    r.damageScore.value_or(-1), r.damageVerdict.c_str());
        EXPECT_EQ(r.flagScore, expected);
        EXPECT_EQ(r.damageVerdict, *r.damageScore >= expected ? "damaged" : "clean");
    }
    EXPECT_EQ(regs2["s1"].damageVerdict, "clean") << "no longer a false alarm";
    EXPECT_EQ(alertsOf("damaged").size(), 5u + (regs2["s3"].damaged ? 1u : 0u));

    // Cleared: back to the station file's 0.5.
    auto cleared =
        cli2.Post("/api/damage/threshold", auth, R"({"flag_score": null})", "application/json");
    ASSERT_EQ(cleared->status, 200);
    EXPECT_EQ(nlohmann::json::parse(cleared->body)["source"], "station file");
    EXPECT_DOUBLE_EQ(nlohmann::json::parse(cleared->body)["flag_score"].get<double>(), 0.5);
}
