// The station end to end in one process: simulated stage and camera over a virtual slide of
// generated sections (one torn), the built-in atlas, a real SQLite journal and real files.
// Whole runs, rescans, every fault policy, and the HTTP API over real HTTP.
#include "slicestation/daemon/config_document.hpp"
#include "slicestation/daemon/http_api.hpp"
#include "slicestation/daemon/ome_tiff.hpp"
#include "slicestation/daemon/station.hpp"
#include "slicestation/sim/faulty_camera.hpp"
#include "slicestation/sim/faulty_stage.hpp"
#include "slicestation/sim/sim_camera.hpp"
#include "slicestation/sim/sim_stage.hpp"
#include "slicestation/sim/virtual_slide.hpp"

#include <gtest/gtest.h>
#include <httplib.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <mutex>
#include <thread>

using namespace slicestation;
using namespace slicestation::daemon;
using namespace std::chrono_literals;

namespace {

constexpr double kUmPerPx = 10.0;
constexpr const char* kToken = "test-token-0123456789";

/// Four sections in a row, the third torn; generated once for all tests.
const sim::VirtualSlide& slide() {
    static const sim::VirtualSlide s = [] {
        sim::VirtualSlideSpec spec;
        spec.columns = 4;
        spec.umPerPx = kUmPerPx;
        // Tissue at the atlas's physical size (the generator fills ~75% of the patch; the
        // built-in brain is ~9.7 mm wide), so the known pixel size means what it says.
        spec.sectionWidthUm = 13'000;
        spec.sectionPitchUm = 14'000;
        const double ap[] = {0.35, 0.45, 0.55, 0.65};
        for (int i = 0; i < 4; ++i)
            spec.sections.push_back({ap[i], i == 2 ? "tear" : "", static_cast<std::uint64_t>(100 + i)});
        auto r = sim::makeVirtualSlide(spec);
        if (!r) throw std::runtime_error(r.error().message);
        return *r;
    }();
    return s;
}

/// The plan for the slide: slice index = apFraction * 8000 um / 100 um.
nlohmann::json planFor(const std::vector<int>& which, const std::string& name = "test-run") {
    nlohmann::json secs = nlohmann::json::array();
    for (int i : which) {
        const auto& s = slide().sections[static_cast<std::size_t>(i)];
        secs.push_back({{"name", "s" + std::to_string(i + 1)},
                        {"x_um", s.centre.xUm},
                        {"y_um", s.centre.yUm},
                        {"atlas_slice", static_cast<int>(std::lround(s.apFraction * 80))}});
    }
    return {{"name", name}, {"slides", {{{"name", "slide-01"}, {"sections", secs}}}}};
}

struct Rig {
    std::filesystem::path dir;
    sim::FaultyStage* stage = nullptr;
    sim::FaultyCamera* camera = nullptr;
    std::unique_ptr<Station> station;
    std::unique_ptr<HttpApi> api;
    std::shared_ptr<std::mutex> posMutex = std::make_shared<std::mutex>();
    std::shared_ptr<hw::StagePosition> pos = std::make_shared<hw::StagePosition>();
    std::uint64_t freeBytes = 100ull << 30;
};

class StationTest : public ::testing::Test {
protected:
    void SetUp() override {
        rig_.dir = std::filesystem::temp_directory_path() /
                   ("slst-station-" + std::to_string(::getpid()) + "-" +
                    ::testing::UnitTest::GetInstance()->current_test_info()->name());
        std::filesystem::remove_all(rig_.dir);
    }
    void TearDown() override {
        if (rig_.api) rig_.api->stop();
        if (rig_.station) rig_.station->stop();
        rig_.station.reset();
        std::filesystem::remove_all(rig_.dir);
    }

    /// Builds the station (not started). `scanToml` overrides [scan] keys.
    void build(const std::string& scanExtra = "") {
        sim::SimStageConfig sc;
        sc.clock = std::make_shared<core::VirtualClock>(); // moves complete at once
        sc.start = {0, 0, 2'500};
        auto simStage = sim::SimStage::create(sc);
        ASSERT_TRUE(simStage);
        auto stage = sim::FaultyStage::create(std::move(*simStage), nullptr);
        ASSERT_TRUE(stage);
        rig_.stage = stage->get();
        sim::SimCameraConfig cc;
        cc.sensorUmPerPx = kUmPerPx;
        auto pos = rig_.pos;
        auto mu = rig_.posMutex;
        cc.stagePosition = [pos, mu] {
            std::lock_guard lock(*mu);
            return *pos;
        };
        auto simCamera = sim::SimCamera::create(slide(), cc);
        ASSERT_TRUE(simCamera) << simCamera.error().message;
        auto camera = sim::FaultyCamera::create(std::move(*simCamera), std::make_shared<core::VirtualClock>());
        ASSERT_TRUE(camera);
        rig_.camera = camera->get();

        auto doc = parseDocument(std::string("[daemon]\ntoken = \"") + kToken + "\"\n[scan]\num_per_px = " +
                                     std::to_string(kUmPerPx) + "\nwidth = 1280\nheight = 1024\n" + scanExtra,
                                 DocumentFormat::Toml, "station.toml");
        ASSERT_TRUE(doc) << doc.error().message;
        auto settings = parseDaemonSettings(*doc, "station.toml");
        ASSERT_TRUE(settings) << settings.error().message;
        StationParts parts;
        parts.stage = std::move(*stage);
        parts.camera = std::move(*camera);
        parts.simulatedStage = parts.simulatedCamera = true;
        parts.settings = *settings;
        parts.stateDir = rig_.dir;
        std::uint64_t* freeBytes = &rig_.freeBytes;
        parts.freeSpace = [freeBytes](const std::filesystem::path&) -> core::Result<std::uint64_t> { return *freeBytes; };
        parts.stageMoved = [pos, mu](const hw::StagePosition& p) {
            std::lock_guard lock(*mu);
            *pos = p;
        };
        auto st = Station::create(std::move(parts));
        ASSERT_TRUE(st) << st.error().message;
        rig_.station = std::move(*st);
    }

    /// Waits (bounded) until the run reaches `state`.
    RunRecord waitRun(std::int64_t id, RunState state, std::chrono::seconds limit = 300s) {
        const auto deadline = std::chrono::steady_clock::now() + limit;
        for (;;) {
            auto r = rig_.station->journal().run(id);
            EXPECT_TRUE(r);
            if (!r) return {};
            if (r->state == state && (state != RunState::Finished || rig_.station->idle())) return *r;
            if (std::chrono::steady_clock::now() > deadline) {
                ADD_FAILURE() << "run " << id << " is " << toString(r->state) << " (" << r->reason
                              << "), expected " << toString(state);
                return *r;
            }
            std::this_thread::sleep_for(50ms); // polling the journal, not waiting for time to pass
        }
    }

    std::vector<AlertRecord> alertsOf(const std::string& kind) {
        std::vector<AlertRecord> out;
        auto all = rig_.station->journal().alerts(false);
        EXPECT_TRUE(all);
        if (!all) return out;
        for (const auto& a : *all)
            if (a.kind == kind) out.push_back(a);
        return out;
    }

    Rig rig_;
};

} // namespace

TEST_F(StationTest, AWholeRunStoresEverySectionRegistersItAndFlagsTheTornOne) {
    build();
    auto id = rig_.station->submitPlan(planFor({0, 1, 2, 3}), "plan");
    ASSERT_TRUE(id) << id.error().message;
    rig_.station->start();
    const RunRecord run = waitRun(*id, RunState::Finished);
    EXPECT_EQ(run.doneCount, 4);

    auto secs = rig_.station->journal().sections(*id);
    ASSERT_TRUE(secs);
    ASSERT_EQ(secs->size(), 4u);
    for (const auto& s : *secs) {
        SCOPED_TRACE(s.name);
        auto caps = rig_.station->journal().captures(s.id);
        ASSERT_EQ(caps->size(), 1u) << "each section captured exactly once";
        const auto& c = caps->front();
        // The file is complete, carries its pixel size and stage position.
        auto img = readOmeTiff(rig_.dir / c.imagePath);
        ASSERT_TRUE(img) << img.error().message;
        EXPECT_DOUBLE_EQ(img->info.umPerPx, kUmPerPx);
        EXPECT_NEAR(img->info.stage.xUm, s.xUm, 1.0);
        EXPECT_NEAR(img->info.stage.yUm, s.yUm, 1.0);
        EXPECT_EQ(img->image.cols, 1280);
        // Focus found near the simulated focal surface (2500 + 0.002 x - 0.001 y).
        EXPECT_TRUE(c.focusFound);
        EXPECT_NEAR(c.stage.zUm, 2'500 + 0.002 * s.xUm - 0.001 * s.yUm, 10.0);
        auto regs = rig_.station->journal().registrations(s.id);
        ASSERT_EQ(regs->size(), 1u);
        const auto& r = regs->front();
        EXPECT_EQ(r.atlasSlice, s.expectedSlice.value());
        EXPECT_TRUE(std::filesystem::exists(rig_.dir / r.overlayPath));
        EXPECT_TRUE(std::filesystem::exists(rig_.dir / r.labelsPath));
        EXPECT_GT(r.quality, 0.8) << "the atlas overlaps the tissue";
        // The matched slice is recorded; a warning exactly when it is beyond the tolerance
        // (matching accuracy itself is measured by slst_bench_atlas_match).
        ASSERT_TRUE(r.matchedSlice.has_value());
        EXPECT_EQ(r.warning.empty(), std::abs(*r.matchedSlice - r.atlasSlice) <= 2) << r.warning;
        if (s.name == "s3") {
            EXPECT_TRUE(r.damaged) << r.summary;
            EXPECT_EQ(s.state, SectionState::Damaged);
        } else {
            EXPECT_FALSE(r.damaged) << r.summary;
            EXPECT_EQ(s.state, SectionState::Registered);
        }
    }
    auto damaged = alertsOf("damaged");
    ASSERT_EQ(damaged.size(), 1u);
    EXPECT_EQ(damaged[0].sectionId, (*secs)[2].id);
    EXPECT_EQ(alertsOf("run_finished").size(), 1u);
    EXPECT_TRUE(rig_.station->journal().checkIntegrity());
    // Phases were timed.
    auto phases = rig_.station->stats().summary();
    for (const char* p : {"move", "focus", "capture", "write", "register"}) EXPECT_TRUE(phases.contains(p)) << p;

    // Export: one row per section, CSV and JSON.
    auto csv = rig_.station->exportRun(*id, "csv");
    ASSERT_TRUE(csv);
    EXPECT_EQ(std::count(csv->begin(), csv->end(), '\n'), 5);
    EXPECT_NE(csv->find("damaged"), std::string::npos);
    auto json = rig_.station->exportRun(*id, "json");
    ASSERT_TRUE(json);
    EXPECT_EQ(nlohmann::json::parse(*json)["sections"].size(), 4u);
    EXPECT_EQ(rig_.station->exportRun(*id, "xml").error().code, core::ErrorCode::InvalidArgument);

    // Re-mounted: a rescan captures the torn section again and keeps both records.
    ASSERT_TRUE(rig_.station->requestRescan((*secs)[2].id));
    waitRun(*id, RunState::Finished);
    EXPECT_EQ(rig_.station->journal().captures((*secs)[2].id)->size(), 2u);
    EXPECT_EQ(rig_.station->journal().registrations((*secs)[2].id)->size(), 2u);
    EXPECT_EQ(rig_.station->journal().captures((*secs)[0].id)->size(), 1u);
}

TEST_F(StationTest, AStageAlarmPausesTheRunUntilResumed) {
    build();
    rig_.stage->alarmOnNextMove(0x28);
    auto id = rig_.station->submitPlan(planFor({0}), "plan");
    ASSERT_TRUE(id);
    rig_.station->start();
    const RunRecord paused = waitRun(*id, RunState::Paused);
    EXPECT_NE(paused.reason.find("stage_fault"), std::string::npos) << paused.reason;
    ASSERT_EQ(alertsOf("stage_fault").size(), 1u);
    EXPECT_EQ(alertsOf("run_paused").size(), 1u);
    EXPECT_EQ(rig_.station->journal().captures((*rig_.station->journal().sections(*id))[0].id)->size(), 0u);
    // The technician clears the alarm and resumes (the scan loop is idle: the run is paused).
    ASSERT_TRUE(rig_.stage->resetAlarm(1s));
    ASSERT_TRUE(rig_.station->scanner().resume(*id));
    waitRun(*id, RunState::Finished);
    EXPECT_EQ(rig_.station->journal().captures((*rig_.station->journal().sections(*id))[0].id)->size(), 1u);
}

TEST_F(StationTest, CameraTimeoutsBeyondTheRetriesPauseTheRunAndRetriesWithinThemDoNot) {
    build("capture_retries = 2\nautofocus = false\n");
    rig_.camera->timeoutNext(2); // two timeouts: the third attempt succeeds
    auto id = rig_.station->submitPlan(planFor({0}), "plan");
    ASSERT_TRUE(id);
    rig_.station->start();
    waitRun(*id, RunState::Finished);
    EXPECT_TRUE(alertsOf("camera_fault").empty());

    rig_.camera->timeoutNext(10); // safe: the scan loop is idle now
    auto id2 = rig_.station->submitPlan(planFor({1}, "second"), "plan");
    ASSERT_TRUE(id2);
    const RunRecord paused = waitRun(*id2, RunState::Paused);
    EXPECT_NE(paused.reason.find("camera_fault"), std::string::npos) << paused.reason;
    EXPECT_EQ(alertsOf("camera_fault").size(), 1u);
}

TEST_F(StationTest, LowDiskPausesBeforeAnythingIsWritten) {
    build();
    rig_.freeBytes = 100ull << 20; // 100 MB < 500 MB threshold
    auto id = rig_.station->submitPlan(planFor({0, 1}), "plan");
    ASSERT_TRUE(id);
    rig_.station->start();
    const RunRecord paused = waitRun(*id, RunState::Paused);
    EXPECT_NE(paused.reason.find("low disk"), std::string::npos) << paused.reason;
    EXPECT_EQ(alertsOf("low_disk").size(), 1u);
    EXPECT_FALSE(std::filesystem::exists(rig_.dir / "runs"));
}

TEST_F(StationTest, CancelStopsTheRunAndIsReportedOnce) {
    build();
    auto id = rig_.station->submitPlan(planFor({0, 1, 2, 3}), "plan");
    ASSERT_TRUE(id);
    ASSERT_TRUE(rig_.station->scanner().cancel(*id)); // not started yet: at once
    EXPECT_EQ(rig_.station->journal().run(*id)->state, RunState::Cancelled);
    EXPECT_EQ(alertsOf("run_cancelled").size(), 1u);
    EXPECT_EQ(rig_.station->scanner().cancel(*id).error().code, core::ErrorCode::InvalidArgument);
    EXPECT_EQ(rig_.station->scanner().resume(*id).error().code, core::ErrorCode::InvalidArgument);
    EXPECT_EQ(rig_.station->scanner().pause(424242).error().code, core::ErrorCode::NotFound);
}

TEST_F(StationTest, PlansAreValidatedAgainstTheStationBeforeAnythingIsStored) {
    build();
    auto plan = planFor({0});
    plan["slides"][0]["sections"][0]["x_um"] = 90'000; // beyond the 75 mm stage
    auto r = rig_.station->submitPlan(plan, "plan.toml");
    ASSERT_FALSE(r);
    EXPECT_EQ(r.error().code, core::ErrorCode::InvalidArgument);
    EXPECT_NE(r.error().message.find("slides[0].sections[0].x_um"), std::string::npos) << r.error().message;
    plan = planFor({0});
    plan["slides"][0]["sections"][0]["atlas_slice"] = 500;
    r = rig_.station->submitPlan(plan, "plan.toml");
    ASSERT_FALSE(r);
    EXPECT_NE(r.error().message.find("atlas_slice"), std::string::npos);
    EXPECT_TRUE(rig_.station->journal().runs()->empty());
}

TEST_F(StationTest, HttpApiServesReadsAndGuardsControl) {
    build();
    auto api = HttpApi::start(*rig_.station, "127.0.0.1", 0, kToken);
    ASSERT_TRUE(api) << api.error().message;
    rig_.api = std::move(*api);
    httplib::Client cli("127.0.0.1", rig_.api->port());
    const httplib::Headers auth{{"Authorization", std::string("Bearer ") + kToken}};

    auto st = cli.Get("/api/status");
    ASSERT_TRUE(st);
    EXPECT_EQ(st->status, 200);
    EXPECT_TRUE(nlohmann::json::parse(st->body)["simulated"]["stage"].get<bool>());

    // The planned slices of the front and back sections swapped (mounted out of order, 24
    // slices apart): both get a warning.
    auto swapped = planFor({0, 3});
    std::swap(swapped["slides"][0]["sections"][0]["atlas_slice"], swapped["slides"][0]["sections"][1]["atlas_slice"]);
    const std::string plan = swapped.dump();
    auto noToken = cli.Post("/api/runs", plan, "application/json");
    ASSERT_TRUE(noToken);
    EXPECT_EQ(noToken->status, 401);
    auto wrong = cli.Post("/api/runs", httplib::Headers{{"Authorization", "Bearer nope"}}, plan, "application/json");
    EXPECT_EQ(wrong->status, 401);
    EXPECT_TRUE(rig_.station->journal().runs()->empty());

    auto bad = cli.Post("/api/runs", auth, "name = 3\n", "application/toml");
    ASSERT_TRUE(bad);
    EXPECT_EQ(bad->status, 400);
    EXPECT_NE(bad->body.find("name: expected a string"), std::string::npos);

    auto ok = cli.Post("/api/runs", auth, plan, "application/json");
    ASSERT_TRUE(ok);
    ASSERT_EQ(ok->status, 201) << ok->body;
    const auto runId = nlohmann::json::parse(ok->body)["run_id"].get<std::int64_t>();
    rig_.station->start();
    waitRun(runId, RunState::Finished);

    auto runs = cli.Get("/api/runs");
    EXPECT_EQ(nlohmann::json::parse(runs->body).size(), 1u);
    auto secs = cli.Get("/api/runs/" + std::to_string(runId) + "/sections");
    ASSERT_EQ(secs->status, 200);
    const auto sj = nlohmann::json::parse(secs->body);
    ASSERT_EQ(sj.size(), 2u);
    auto detail = cli.Get("/api/sections/" + std::to_string(sj[0]["id"].get<std::int64_t>()));
    ASSERT_EQ(detail->status, 200);
    const auto dj = nlohmann::json::parse(detail->body);
    EXPECT_EQ(dj["captures"].size(), 1u);
    EXPECT_EQ(dj["registrations"].size(), 1u);
    for (const auto& sec : sj) {
        const auto d = nlohmann::json::parse(cli.Get("/api/sections/" + std::to_string(sec["id"].get<std::int64_t>()))->body);
        EXPECT_NE(d["registrations"][0]["warning"].get<std::string>().find("mounted out of order"), std::string::npos)
            << sec["name"];
    }
    auto csv = cli.Get("/api/runs/" + std::to_string(runId) + "/export?format=csv");
    EXPECT_EQ(csv->status, 200);
    EXPECT_EQ(csv->get_header_value("Content-Type"), "text/csv");

    // Bad ids, unknown records, traversal attempts: 4xx, never a file.
    EXPECT_EQ(cli.Get("/api/sections/abc")->status, 400);
    EXPECT_EQ(cli.Get("/api/sections/99999")->status, 404);
    for (const char* evil : {"/api/runs/1%2F..%2F..%2Fjournal.sqlite", "/api/../journal.sqlite",
                             "/api/sections/..%2Fjournal.sqlite", "/journal.sqlite", "/api/runs/1/../../journal.sqlite"}) {
        auto r = cli.Get(evil);
        ASSERT_TRUE(r) << evil;
        EXPECT_TRUE(r->status == 400 || r->status == 404) << evil << " -> " << r->status;
        EXPECT_EQ(r->body.find("SQLite format"), std::string::npos) << evil;
    }
    EXPECT_EQ(cli.Get("/api/runs/" + std::to_string(runId) + "/export?format=../../etc/passwd")->status, 400);

    // Control: pause a finished run is a conflict; acknowledging an alert works once.
    EXPECT_EQ(cli.Post("/api/runs/" + std::to_string(runId) + "/pause", auth, "", "text/plain")->status, 409);
    auto alerts = nlohmann::json::parse(cli.Get("/api/alerts?open=1")->body);
    ASSERT_FALSE(alerts.empty());
    const std::string ackPath = "/api/alerts/" + std::to_string(alerts[0]["id"].get<std::int64_t>()) + "/ack";
    EXPECT_EQ(cli.Post(ackPath, "{\"action\":\"accept\"}", "application/json")->status, 401);
    EXPECT_EQ(cli.Post(ackPath, auth, "{\"action\": 5}", "application/json")->status, 400);
    EXPECT_EQ(cli.Post(ackPath, auth, "{\"action\":\"accept\"}", "application/json")->status, 200);
    EXPECT_EQ(cli.Post(ackPath, auth, "{\"action\":\"accept\"}", "application/json")->status, 409);
}
