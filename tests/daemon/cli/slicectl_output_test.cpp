// slicectl for people (issue 23): tables and --json against a daemon's HTTP API (served in this
// process over a scripted station), local times, exit codes, "did you mean", --action checked,
// --version of both programs, plain numbers, and the progress line.
#include "../../web/scripted_station.hpp"
#include "slicestation/daemon/cli/atlas_command.hpp"
#include "slicestation/daemon/cli/cli_output.hpp"
#include "slicestation/daemon/cli/demo_command.hpp"
#include "slicestation/daemon/cli/register_command.hpp"
#include "slicestation/daemon/http/http_api.hpp"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <sys/wait.h>

#include <array>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <utility>
#include <vector>

using namespace slicestation;
using namespace slicestation::daemon;
using namespace slicestation::testing_web;

namespace {

constexpr const char* kToken = "cli-token-0123456789";

struct Run {
    int code = -1;
    std::string out; ///< stdout
    std::string all; ///< stdout and stderr
};

/// Runs `program args` with TZ=Asia/Kolkata; stdout alone, and stdout+stderr.
Run run(const std::string& program, const std::string& args) {
    Run r;
    const std::string base = "TZ=Asia/Kolkata " + program + " " + args;
    auto capture = [](const std::string& cmd, std::string& into) {
        FILE* p = ::popen(cmd.c_str(), "r");
        std::array<char, 4096> buf{};
        while (p && std::fgets(buf.data(), buf.size(), p))
            into += buf.data();
        const int status = p ? ::pclose(p) : -1;
        return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
    };
    r.code = capture(base + " 2>/dev/null", r.out);
    capture(base + " 2>&1", r.all);
    return r;
}
Run slicectl(const std::string& args) {
    return run(SLICECTL_PATH, args);
}

class SlicectlDaemon : public ::testing::Test {
protected:
    void SetUp() override {
        station_.registerSection(103, true, 0.062);
        station_.addAlert(makeAlert(21, 103, "damaged", "critical",
                                    "slide-01/s03 is damaged (tear): re-mount it",
                                    "2026-12-02T09:32:00.000Z"));
        auto api = HttpApi::start(station_, "127.0.0.1", 0, kToken);
        ASSERT_TRUE(api) << api.error().message;
        api_ = std::move(*api);
        url_ = " --url http://127.0.0.1:" + std::to_string(api_->port());
    }
    void TearDown() override {
        if (api_)
            api_->stop();
    }
    ScriptedStation station_;
    std::unique_ptr<HttpApi> api_;
    std::string url_;
};

} // namespace

TEST_F(SlicectlDaemon, TablesForPeopleJsonForScripts) {
    auto r = slicectl("runs" + url_);
    ASSERT_EQ(r.code, 0) << r.all;
    EXPECT_NE(r.out.find("ID  NAME"), std::string::npos) << r.out;
    EXPECT_NE(r.out.find("mouse-42"), std::string::npos) << r.out;
    // 09:30 UTC in Kolkata, labelled.
    EXPECT_NE(r.out.find("2026-12-02 15:00:00"), std::string::npos) << r.out;
    EXPECT_NE(r.out.find("(local time, IST (UTC+05:30))"), std::string::npos) << r.out;
    r = slicectl("runs --json" + url_);
    ASSERT_EQ(r.code, 0) << r.all;
    const auto runs = nlohmann::json::parse(r.out);
    ASSERT_EQ(runs.size(), 2u);
    EXPECT_EQ(runs[1]["created_utc"], "2026-12-02T09:30:00.000Z");

    r = slicectl("sections 7" + url_);
    ASSERT_EQ(r.code, 0) << r.all;
    EXPECT_NE(r.out.find("ID   SLIDE     SECTION  STATE"), std::string::npos) << r.out;
    EXPECT_NE(r.out.find("103  slide-01  s03      damaged"), std::string::npos) << r.out;
    EXPECT_EQ(nlohmann::json::parse(slicectl("sections 7 --json" + url_).out).size(), 4u);

    r = slicectl("alerts" + url_);
    ASSERT_EQ(r.code, 0) << r.all;
    EXPECT_NE(r.out.find("21  2026-12-02 15:02:00  critical  damaged  103      open"),
              std::string::npos)
        << r.out;
    r = slicectl("status" + url_);
    ASSERT_EQ(r.code, 0) << r.all;
    EXPECT_NE(r.out.find("state"), std::string::npos) << r.out;
    EXPECT_NE(r.out.find("#7 mouse-42, running, 1/4 sections"), std::string::npos) << r.out;
    EXPECT_EQ(nlohmann::json::parse(slicectl("status --json" + url_).out)["state"], "scanning");
}

TEST_F(SlicectlDaemon, ExitCodesSayWhatWentWrong) {
    // 0: done, one line.
    auto r = slicectl("pause 7 --token " + std::string(kToken) + url_);
    EXPECT_EQ(r.code, 0) << r.all;
    EXPECT_EQ(r.out, "run 7: pause requested (it stops between sections)\n");
    // 4: a conflict with the run's state (paused already: pause again is refused with 409).
    r = slicectl("pause 7 --token " + std::string(kToken) + url_);
    EXPECT_EQ(r.code, 4) << r.all;
    EXPECT_NE(r.all.find("HTTP 409"), std::string::npos) << r.all;
    // 3: refused (no token), and unreachable.
    r = slicectl("resume 7" + url_);
    EXPECT_EQ(r.code, 3) << r.all;
    EXPECT_NE(r.all.find("HTTP 401"), std::string::npos) << r.all;
    r = slicectl("status --url http://127.0.0.1:1");
    EXPECT_EQ(r.code, 3) << r.all;
    EXPECT_NE(r.all.find("cannot reach slicestationd"), std::string::npos) << r.all;
    // 2: input: no such record; a value not allowed (checked before anything is sent).
    r = slicectl("sections 99" + url_);
    EXPECT_EQ(r.code, 2) << r.all;
    r = slicectl("alerts ack 21 --action maybe --token " + std::string(kToken) + url_);
    EXPECT_EQ(r.code, 2) << r.all;
    EXPECT_NE(r.all.find("--action"), std::string::npos) << r.all;
    EXPECT_FALSE(station_.called("ack maybe 21"));
    r = slicectl("alerts ack 21 --action rescan --token " + std::string(kToken) + url_);
    EXPECT_EQ(r.code, 0) << r.all;
    EXPECT_TRUE(station_.called("ack rescan 21"));
    // 1: usage, with a suggestion for a mistyped command.
    r = slicectl("regster --image x.tif");
    EXPECT_EQ(r.code, 1) << r.all;
    EXPECT_NE(r.all.find("did you mean \"register\"?"), std::string::npos) << r.all;
    r = slicectl("atlas slcie --builtin");
    EXPECT_EQ(r.code, 1) << r.all;
    EXPECT_NE(r.all.find("did you mean \"atlas slice\"?"), std::string::npos) << r.all;
    r = slicectl("sections");
    EXPECT_EQ(r.code, 1) << r.all;
}

TEST(SlicectlVersion, BothProgramsPrintTheBuildsVersion) {
    auto r = run(SLICECTL_PATH, "--version");
    EXPECT_EQ(r.code, 0);
    EXPECT_EQ(r.out, std::string("slicectl ") + SLST_PROJECT_VERSION + "\n");
    r = run(SLICESTATIOND_PATH, "--version");
    EXPECT_EQ(r.code, 0);
    EXPECT_EQ(r.out, std::string("slicestationd ") + SLST_PROJECT_VERSION + "\n");
}

TEST(SlicectlOutput, NumbersAsPeopleWriteThem) {
    EXPECT_EQ(plainNumber(75000.0), "75000");
    EXPECT_EQ(plainNumber(0.0), "0");
    EXPECT_EQ(plainNumber(-0.0), "0");
    EXPECT_EQ(plainNumber(12345.5), "12345.5");
    EXPECT_EQ(plainNumber(0.25), "0.25");
    EXPECT_EQ(plainNumber(-100000.0), "-100000");
    EXPECT_EQ(plainNumber(123456789012.0), "123456789012");
    EXPECT_EQ(plainNumber(1e-6), "1e-06"); // tiny magnitudes keep the exponent
    // The help of a range check says [1, 20000], not [1.000000, 20000.000000].
    const auto r = slicectl("atlas slice --help");
    EXPECT_NE(r.out.find("FINITE in [1, 20000]"), std::string::npos) << r.out;
    EXPECT_EQ(r.out.find(".000000"), std::string::npos) << r.out;
}

TEST(SlicectlOutput, TablesTimesAndSuggestions) {
    EXPECT_EQ(formatTable({"ID", "NAME"}, {{"1", "a"}, {"100", "bbb"}}),
              "ID   NAME\n1    a\n100  bbb\n");
    ::setenv("TZ", "Asia/Kolkata", 1);
    ::tzset();
    EXPECT_EQ(localTime("2026-12-02T09:30:00.000Z"), "2026-12-02 15:00:00");
    EXPECT_EQ(localTime("2026-12-31T20:00:00Z"), "2027-01-01 01:30:00");
    EXPECT_EQ(localTime(""), "");
    EXPECT_EQ(localTime("yesterday"), "yesterday");
    EXPECT_NE(localZoneLabel().find("UTC+05:30"), std::string::npos) << localZoneLabel();
    ::unsetenv("TZ");
    ::tzset();

    CLI::App app;
    app.add_subcommand("register");
    app.add_subcommand("runs");
    app.add_subcommand("rescan");
    auto* atlas = app.add_subcommand("atlas");
    atlas->add_subcommand("slice");
    atlas->add_subcommand("match");
    EXPECT_EQ(nearestSubcommand(app, "regster"), "register");
    EXPECT_EQ(nearestSubcommand(app, "rus"), "runs");
    EXPECT_EQ(nearestSubcommand(app, "reg"), "register"); // a prefix
    EXPECT_EQ(nearestSubcommand(app, "zzzzzz"), "");
    std::array<const char*, 3> argv{"slicectl", "atlas", "mach"};
    EXPECT_EQ(didYouMean(app, 3, const_cast<char**>(argv.data())),
              "unknown command \"atlas mach\"; did you mean \"atlas match\"?");
    std::array<const char*, 3> ok{"slicectl", "runs", "--json"};
    EXPECT_EQ(didYouMean(app, 3, const_cast<char**>(ok.data())), "");
}

TEST(SlicectlOutput, TheProgressLineAndItsSilenceOffATerminal) {
    {
        Progress on("atlas slice", true);
        on.phase("collapsing regions", 80);
        on.advance(40);
        const std::string l = on.line();
        EXPECT_EQ(l.rfind("slicectl atlas slice: collapsing regions [############            ] "
                          "40/80  ",
                          0),
                  0u)
            << l;
        EXPECT_TRUE(l.ends_with(" s")) << l;
        on.phase("writing the stack");
        EXPECT_NE(on.line().find("writing the stack "), std::string::npos);
    }
    // A command run by a script (stderr not a terminal) prints no progress at all.
    const auto r = slicectl(
        "atlas slice --builtin --interval-um 2000 --output " +
        (std::filesystem::temp_directory_path() / ("slst_progress_" + std::to_string(::getpid())))
            .string());
    ASSERT_EQ(r.code, 0) << r.all;
    EXPECT_EQ(r.all.find("slicectl atlas slice:"), std::string::npos) << r.all;
    EXPECT_EQ(r.all.find('\r'), std::string::npos) << r.all;
    std::filesystem::remove_all(std::filesystem::temp_directory_path() /
                                ("slst_progress_" + std::to_string(::getpid())));
}

// The bars of `register` and `atlas match` (issue 23 item 4): registration reports its steps
// done of kRegistrationSteps, matching its candidates done of a total that is exact once the
// shortlist is chosen; both end full, never go back, and the line draws them as a bar.
TEST(SlicectlOutput, RegistrationAndMatchingReportProgressForTheBar) {
    const auto dir =
        std::filesystem::temp_directory_path() / ("slst_bars_" + std::to_string(::getpid()));
    std::filesystem::remove_all(dir);
    DemoRequest demo;
    demo.outputDir = dir;
    ASSERT_TRUE(runDemo(demo));
    const auto increasing = [](const std::vector<std::pair<int, int>>& calls) {
        for (std::size_t k = 1; k < calls.size(); ++k)
            if (calls[k].first < calls[k - 1].first || calls[k].first > calls[k].second)
                return false;
        return true;
    };
    RegisterRequest rq;
    rq.atlas = dir / "atlas-labels.tif";
    rq.image = dir / "section.tif";
    rq.output = dir / "again.json";
    std::vector<std::pair<int, int>> steps;
    rq.progress = [&](int done, int total) { steps.emplace_back(done, total); };
    auto reg = runRegister(rq);
    ASSERT_TRUE(reg) << reg.error().message;
    ASSERT_GE(steps.size(), 8u) << "a call after each step";
    EXPECT_TRUE(increasing(steps));
    EXPECT_EQ(steps.back(),
              std::make_pair(pipeline::kRegistrationSteps, pipeline::kRegistrationSteps));
    for (const auto& s : steps)
        EXPECT_EQ(s.second, pipeline::kRegistrationSteps);

    AtlasSliceRequest slice;
    slice.builtin = true;
    slice.intervalUm = 500;
    slice.output = dir / "stack";
    ASSERT_TRUE(runAtlasSlice(slice));
    AtlasMatchRequest match;
    match.stack = dir / "stack";
    match.image = dir / "section.tif";
    match.output = dir / "match.json";
    std::vector<std::pair<int, int>> candidates;
    std::vector<std::string> phases;
    match.progress = [&](const std::string& phase, int done, int total) {
        if (phases.empty() || phases.back() != phase)
            phases.push_back(phase);
        if (phase == "matching against the slices")
            candidates.emplace_back(done, total);
    };
    auto m = runAtlasMatch(match);
    ASSERT_TRUE(m) << m.error().message;
    EXPECT_EQ(phases, (std::vector<std::string>{"reading the stack's slices",
                                                "matching against the slices"}));
    ASSERT_GE(candidates.size(), 5u);
    EXPECT_TRUE(increasing(candidates));
    EXPECT_EQ(candidates.back().first, candidates.back().second) << "the bar ends full";
    std::cout << "register: " << steps.size()
              << " progress calls; atlas match: " << candidates.size() << " of "
              << candidates.back().second << "\n";

    Progress bar("atlas match", true);
    bar.phase("matching against the slices", 20);
    bar.advance(5, 40); // the total became exact
    EXPECT_NE(bar.line().find("[###                     ] 5/40"), std::string::npos) << bar.line();
    std::filesystem::remove_all(dir);
}
