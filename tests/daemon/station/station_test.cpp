// The station end to end in one process: simulated stage and camera over a virtual slide of
// generated sections (one torn), the built-in atlas, a real SQLite journal and real files.
// Whole runs, rescans, every fault policy, and the HTTP API over real HTTP.
#include "full_disk_vfs.hpp"
#include "station_fixture.hpp"

#include "slicestation/core/tiff_file.hpp"
#include "slicestation/core/unique_fd.hpp"
#include "slicestation/daemon/storage/ome_tiff.hpp"

#include <gtest/gtest.h>
#include <httplib.h>
#include <opencv2/imgcodecs.hpp>

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <set>
#include <thread>

using namespace slicestation;
using namespace slicestation::daemon;
using namespace std::chrono_literals;

using namespace slicestation::testing_station;

TEST_F(StationTest, AWholeRunStoresEverySectionRegistersItAndFlagsTheTornOne) {
    build();
    const RunRecord run = runToTheEnd(planFor({0, 1, 2, 3}));
    EXPECT_EQ(run.doneCount, 4);

    auto secs = rig_.station->journal().sections(run.id);
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
        // Written as QuPath reads it (docs/images.md): the objective of the station file, the
        // fluorescence channel green, 512 px tiles and one reduced level (1280 -> 640 px).
        EXPECT_EQ(img->info.objective, rig_.station->settings().scan.objective.name);
        EXPECT_EQ(img->info.channelRgba, 0x00FF00FFu);
        auto pyramid = core::readTiffPyramidInfo(rig_.dir / c.imagePath);
        ASSERT_TRUE(pyramid) << pyramid.error().message;
        EXPECT_TRUE(pyramid->tiled);
        EXPECT_EQ(pyramid->tileSize, cv::Size(512, 512));
        EXPECT_EQ(pyramid->levels, (std::vector<cv::Size>{{1280, 1024}, {640, 512}}));
        // Focus found near the simulated focal surface (2500 + 0.002 x - 0.001 y).
        EXPECT_TRUE(c.focusFound);
        EXPECT_NEAR(c.stage.zUm, 2'500 + 0.002 * s.xUm - 0.001 * s.yUm, 10.0);
        auto regs = rig_.station->journal().registrations(s.id);
        ASSERT_EQ(regs->size(), 1u);
        const auto& r = regs->front();
        // Registered to the slice the run's series model says; the plan's is recorded beside it.
        EXPECT_EQ(r.plannedSlice, s.expectedSlice);
        ASSERT_TRUE(r.series.has_value());
        const int found = static_cast<int>(std::lround(r.series->positionUm / 100.0));
        EXPECT_EQ(r.atlasSlice, std::abs(found - *s.expectedSlice) > 2 ? found : *s.expectedSlice);
        EXPECT_TRUE(std::filesystem::exists(rig_.dir / r.overlayPath));
        EXPECT_TRUE(std::filesystem::exists(rig_.dir / r.labelsPath));
        EXPECT_GT(r.quality, 0.8) << "the atlas overlaps the tissue";
        // The matched slice is recorded; a warning exactly when it is beyond the tolerance
        // (matching accuracy itself is measured by slst_bench_atlas_match).
        ASSERT_TRUE(r.matchedSlice.has_value());
        EXPECT_EQ(r.warning.empty(), std::abs(found - *s.expectedSlice) <= 2) << r.warning;
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
    for (const char* p : {"move", "focus", "capture", "write", "register"})
        EXPECT_TRUE(phases.contains(p)) << p;

    // Export: one row per section, CSV and JSON.
    auto csv = rig_.station->exportRun(run.id, "csv");
    ASSERT_TRUE(csv);
    EXPECT_EQ(std::count(csv->begin(), csv->end(), '\n'), 5);
    EXPECT_NE(csv->find("damaged"), std::string::npos);
    auto json = rig_.station->exportRun(run.id, "json");
    ASSERT_TRUE(json);
    EXPECT_EQ(nlohmann::json::parse(*json)["sections"].size(), 4u);
    EXPECT_EQ(rig_.station->exportRun(run.id, "xml").error().code,
              core::ErrorCode::InvalidArgument);

    // Re-mounted: a rescan captures the torn section again and keeps both records.
    ASSERT_TRUE(rig_.station->requestRescan((*secs)[2].id));
    waitRun(run.id, RunState::Finished);
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
    EXPECT_EQ(
        rig_.station->journal().captures((*rig_.station->journal().sections(*id))[0].id)->size(),
        0u);
    // The technician clears the alarm and resumes (the scan loop is idle: the run is paused).
    ASSERT_TRUE(rig_.stage->resetAlarm(1s));
    ASSERT_TRUE(rig_.station->scanner().resume(*id));
    waitRun(*id, RunState::Finished);
    EXPECT_EQ(
        rig_.station->journal().captures((*rig_.station->journal().sections(*id))[0].id)->size(),
        1u);
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
    EXPECT_NE(r.error().message.find("slides[0].sections[0].x_um"), std::string::npos)
        << r.error().message;
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
    std::swap(swapped["slides"][0]["sections"][0]["atlas_slice"],
              swapped["slides"][0]["sections"][1]["atlas_slice"]);
    const std::string plan = swapped.dump();
    auto noToken = cli.Post("/api/runs", plan, "application/json");
    ASSERT_TRUE(noToken);
    EXPECT_EQ(noToken->status, 401);
    auto wrong = cli.Post("/api/runs", httplib::Headers{{"Authorization", "Bearer nope"}}, plan,
                          "application/json");
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
        const auto d = nlohmann::json::parse(
            cli.Get("/api/sections/" + std::to_string(sec["id"].get<std::int64_t>()))->body);
        EXPECT_NE(d["registrations"][0]["warning"].get<std::string>().find("mounted out of order"),
                  std::string::npos)
            << sec["name"];
    }
    auto csv = cli.Get("/api/runs/" + std::to_string(runId) + "/export?format=csv");
    EXPECT_EQ(csv->status, 200);
    EXPECT_EQ(csv->get_header_value("Content-Type"), "text/csv");

    // Bad ids, unknown records, traversal attempts: 4xx, never a file.
    EXPECT_EQ(cli.Get("/api/sections/abc")->status, 400);
    EXPECT_EQ(cli.Get("/api/sections/99999")->status, 404);
    for (const char* evil : {"/api/runs/1%2F..%2F..%2Fjournal.sqlite", "/api/../journal.sqlite",
                             "/api/sections/..%2Fjournal.sqlite", "/journal.sqlite",
                             "/api/runs/1/../../journal.sqlite"}) {
        auto r = cli.Get(evil);
        ASSERT_TRUE(r) << evil;
        EXPECT_TRUE(r->status == 400 || r->status == 404) << evil << " -> " << r->status;
        EXPECT_EQ(r->body.find("SQLite format"), std::string::npos) << evil;
    }
    EXPECT_EQ(
        cli.Get("/api/runs/" + std::to_string(runId) + "/export?format=../../etc/passwd")->status,
        400);

    // Control: pause a finished run is a conflict; acknowledging an alert works once.
    EXPECT_EQ(
        cli.Post("/api/runs/" + std::to_string(runId) + "/pause", auth, "", "text/plain")->status,
        409);
    auto alerts = nlohmann::json::parse(cli.Get("/api/alerts?open=1")->body);
    ASSERT_FALSE(alerts.empty());
    const std::string ackPath =
        "/api/alerts/" + std::to_string(alerts[0]["id"].get<std::int64_t>()) + "/ack";
    EXPECT_EQ(cli.Post(ackPath, "{\"action\":\"accept\"}", "application/json")->status, 401);
    EXPECT_EQ(cli.Post(ackPath, auth, "{\"action\": 5}", "application/json")->status, 400);
    EXPECT_EQ(cli.Post(ackPath, auth, "{\"action\":\"accept\"}", "application/json")->status, 200);
    EXPECT_EQ(cli.Post(ackPath, auth, "{\"action\":\"accept\"}", "application/json")->status, 409);
}

TEST_F(StationTest, HttpApiStreamsEventsAndServesImagesAndRegions) {
    build();
    auto api = HttpApi::start(*rig_.station, "127.0.0.1", 0, kToken);
    ASSERT_TRUE(api) << api.error().message;
    rig_.api = std::move(*api);
    const int port = rig_.api->port();
    httplib::Client cli("127.0.0.1", port);
    const httplib::Headers auth{{"Authorization", std::string("Bearer ") + kToken}};
    EXPECT_EQ(cli.Get("/api/live.jpg")->status, 404) << "no frame before the first capture";

    // A browser that connects and then never reads: acquisition must not wait for it.
    core::UniqueFd stalled(::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0));
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(static_cast<std::uint16_t>(port));
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    ASSERT_EQ(::connect(stalled.get(), reinterpret_cast<sockaddr*>(&addr), sizeof addr), 0);
    const std::string get = "GET /api/events HTTP/1.1\r\nHost: x\r\n\r\n";
    ASSERT_EQ(::send(stalled.get(), get.data(), get.size(), 0), static_cast<ssize_t>(get.size()));

    // A reading client collects the stream until the run has finished.
    std::mutex mu;
    std::string stream;
    std::atomic<bool> done{false};
    std::thread reader([&] {
        httplib::Client sse("127.0.0.1", port);
        sse.set_read_timeout(60, 0);
        sse.Get("/api/events", [&](const char* data, std::size_t n) {
            std::lock_guard lock(mu);
            stream.append(data, n);
            return !done.load();
        });
    });
    // The stream is open (its greeting arrived) before anything happens.
    for (int i = 0; i < 200; ++i) {
        {
            std::lock_guard lock(mu);
            if (stream.find(": connected") != std::string::npos)
                break;
        }
        std::this_thread::sleep_for(10ms); // waiting for the greeting
    }
    auto ok = cli.Post("/api/runs", auth, planFor({1, 2}).dump(), "application/json");
    ASSERT_EQ(ok->status, 201) << ok->body;
    const auto runId = nlohmann::json::parse(ok->body)["run_id"].get<std::int64_t>();
    rig_.station->start();
    waitRun(runId, RunState::Finished);
    // The run's end and the damage alert come from two threads (the scanner sees the last
    // section recorded while the registration worker raises its alert): either may be last.
    for (int i = 0; i < 500; ++i) {
        {
            std::lock_guard lock(mu);
            if (stream.find("finished") != std::string::npos &&
                stream.find("event: alert_raised") != std::string::npos)
                break;
        }
        std::this_thread::sleep_for(10ms); // waiting for the last events to arrive
    }
    done = true;
    // An acknowledgement is an event too; it also ends the reader if it still waits.
    auto alerts = nlohmann::json::parse(cli.Get("/api/alerts?open=1")->body);
    ASSERT_FALSE(alerts.empty());
    EXPECT_EQ(
        cli.Post("/api/alerts/" + std::to_string(alerts[0]["id"].get<std::int64_t>()) + "/ack",
                 auth, "{\"action\":\"accept\"}", "application/json")
            ->status,
        200);
    reader.join();
    {
        std::lock_guard lock(mu);
        for (const char* ev : {"event: section_captured", "event: section_registered",
                               "event: section_damaged", "event: alert_raised", "event: run_state"})
            EXPECT_NE(stream.find(ev), std::string::npos) << ev << " missing from:\n" << stream;
        EXPECT_NE(stream.find("data: {"), std::string::npos);
    }

    // Images, scaled as asked and never up.
    auto decode = [](const httplib::Result& r) {
        return cv::imdecode(std::vector<uchar>(r->body.begin(), r->body.end()),
                            cv::IMREAD_UNCHANGED);
    };
    auto live = cli.Get("/api/live.jpg?width=320");
    ASSERT_EQ(live->status, 200);
    EXPECT_EQ(live->get_header_value("Content-Type"), "image/jpeg");
    EXPECT_EQ(decode(live).cols, 320);
    auto secs =
        nlohmann::json::parse(cli.Get("/api/runs/" + std::to_string(runId) + "/sections")->body);
    ASSERT_EQ(secs.size(), 2u);
    const std::string torn = std::to_string(secs[1]["id"].get<std::int64_t>());
    auto image = cli.Get("/api/sections/" + torn + "/image.jpg?width=200");
    ASSERT_EQ(image->status, 200);
    EXPECT_EQ(decode(image).cols, 200);
    auto overlay = cli.Get("/api/sections/" + torn + "/overlay.png?width=300");
    ASSERT_EQ(overlay->status, 200);
    const cv::Mat ov = decode(overlay);
    EXPECT_EQ(ov.cols, 300);
    EXPECT_EQ(ov.channels(), 3);
    EXPECT_EQ(decode(cli.Get("/api/sections/" + torn + "/image.jpg?width=4000")).cols, 1280)
        << "never scaled up";
    for (const char* bad : {"?width=5", "?width=abc", "?width=", "?width=99999"})
        EXPECT_EQ(cli.Get("/api/sections/" + torn + "/image.jpg" + bad)->status, 400) << bad;
    EXPECT_EQ(cli.Get("/api/sections/99999/overlay.png")->status, 404);

    // Regions: the section detail lists them with names; a pixel names its region.
    auto detail = nlohmann::json::parse(cli.Get("/api/sections/" + torn)->body);
    const auto& regions = detail["registrations"][0]["regions"];
    ASSERT_GT(regions.size(), 3u);
    EXPECT_FALSE(regions[0]["name"].get<std::string>().empty());
    EXPECT_GE(regions[0]["share"].get<double>(), regions[1]["share"].get<double>());
    auto centre = cli.Get("/api/sections/" + torn + "/region?x=640&y=512");
    ASSERT_EQ(centre->status, 200);
    const auto cj = nlohmann::json::parse(centre->body);
    EXPECT_GT(cj["id"].get<int>(), 0) << "the centre of a section lies in the brain";
    EXPECT_FALSE(cj["name"].get<std::string>().empty());
    EXPECT_EQ(
        nlohmann::json::parse(cli.Get("/api/sections/" + torn + "/region?x=2&y=2")->body)["id"], 0)
        << "the corner is glass";
    EXPECT_EQ(cli.Get("/api/sections/" + torn + "/region?x=5000&y=2")->status, 400);
    EXPECT_EQ(cli.Get("/api/sections/" + torn + "/region?y=2")->status, 400);
    EXPECT_EQ(cli.Get("/api/sections/" + torn + "/region?x=-1&y=2")->status, 400);
    // The page asks in the pixels of the overlay it shows (here half size).
    auto half = cli.Get("/api/sections/" + torn + "/region?x=320&y=256&of_width=640");
    ASSERT_EQ(half->status, 200);
    EXPECT_EQ(nlohmann::json::parse(half->body)["id"], cj["id"]);
    EXPECT_EQ(nlohmann::json::parse(half->body)["x"], 641);
    EXPECT_EQ(cli.Get("/api/sections/" + torn + "/region?x=3&y=3&of_width=0")->status, 400);

    // The page itself: HTML that loads nothing from elsewhere.
    auto page = cli.Get("/");
    ASSERT_EQ(page->status, 200);
    EXPECT_EQ(page->get_header_value("Content-Type"), "text/html; charset=utf-8");
    EXPECT_NE(page->get_header_value("Content-Security-Policy").find("default-src 'self'"),
              std::string::npos);
    EXPECT_NE(page->body.find("<title>slicestation</title>"), std::string::npos);
    EXPECT_EQ(page->body.find("http://"), std::string::npos) << "no external resources";
    EXPECT_EQ(page->body.find("https://"), std::string::npos) << "no external resources";
}

// ---------------------------------------------------------------------------------------------
// Storage under hostile names, a full disk and crashes (issue 20).

namespace {

/// A plan section at virtual-slide section `i` (as planFor makes them) with another name.
nlohmann::json sectionAt(int i, const std::string& name) {
    auto s = planFor({i})["slides"][0]["sections"][0];
    s["name"] = name;
    return s;
}

/// Alerts delivered to a channel, waited for with a deadline.
struct DeliveredAlerts {
    std::mutex mutex;
    std::condition_variable cv;
    std::vector<AlertRecord> alerts;

    /// The channel keeps `self` alive: the station may outlive the test's scope.
    static Notifier::AlertChannel channel(const std::shared_ptr<DeliveredAlerts>& self) {
        return [self](const AlertRecord& a) {
            std::lock_guard lock(self->mutex);
            self->alerts.push_back(a);
            self->cv.notify_all();
        };
    }
    std::size_t count(const std::string& kind) {
        std::lock_guard lock(mutex);
        return static_cast<std::size_t>(
            std::count_if(alerts.begin(), alerts.end(),
                          [&](const AlertRecord& a) { return toString(a.kind) == kind; }));
    }
    bool waitFor(const std::string& kind, std::chrono::seconds limit = 60s) {
        std::unique_lock lock(mutex);
        return cv.wait_for(lock, limit, [&] {
            return std::any_of(alerts.begin(), alerts.end(),
                               [&](const AlertRecord& a) { return toString(a.kind) == kind; });
        });
    }
};

std::vector<std::filesystem::path> imagesUnder(const std::filesystem::path& dir) {
    std::vector<std::filesystem::path> out;
    if (!std::filesystem::exists(dir))
        return out;
    for (const auto& e : std::filesystem::recursive_directory_iterator(dir))
        if (e.path().filename().string().ends_with(".ome.tif"))
            out.push_back(e.path());
    return out;
}

/// Clears the OME-TIFF writer's injected fault whatever the test does.
struct WriteFault {
    explicit WriteFault(int err) { setOmeTiffWriteFaultForTesting(err); }
    ~WriteFault() { clear(); }
    void clear() { setOmeTiffWriteFaultForTesting(0); }
};

/// The journal's disk fills when a run first goes to "running" (once: not again after a
/// resume), and is emptied again when the test ends, whatever it does.
class JournalFillsOnceRunning {
public:
    JournalFillsOnceRunning(testing_vfs::FullDiskVfs& vfs, Notifier& notifier) : vfs_(vfs) {
        auto filled = std::make_shared<std::atomic<bool>>(false);
        notifier.addListener([&vfs, filled](const StationEvent& e) {
            if (e.type == "run_state" && e.data.value("state", "") == "running" &&
                !filled->exchange(true))
                vfs.setFull(true);
        });
    }
    ~JournalFillsOnceRunning() { vfs_.setFull(false); }
    JournalFillsOnceRunning(const JournalFillsOnceRunning&) = delete;
    JournalFillsOnceRunning& operator=(const JournalFillsOnceRunning&) = delete;

private:
    testing_vfs::FullDiskVfs& vfs_;
};

} // namespace

TEST_F(StationTest, NamesThatLookAlikeAsFileNamesAreStoredInDistinctFiles) {
    build("autofocus = false\n");
    // "s 1" and "s_1", "s01é" and "s01è" on one slide, and slides "slide 1" and "slide_1":
    // each pair has one safe name, and each image went to one file before. ("s/1", the
    // audit's example, is now refused at submit: a name holds no '/'.)
    nlohmann::json plan = {
        {"name", "look-alike"},
        {"slides",
         {{{"name", "slide 1"}, {"sections", {sectionAt(0, "s 1"), sectionAt(1, "s_1")}}},
          {{"name", "slide_1"},
           {"sections", {sectionAt(2, "s 1"), sectionAt(3, "s01é"), sectionAt(1, "s01è")}}}}}};
    const RunRecord run = runToTheEnd(plan);
    EXPECT_EQ(run.doneCount, 5);
    auto secs = rig_.station->journal().sections(run.id);
    ASSERT_TRUE(secs);
    ASSERT_EQ(secs->size(), 5u);
    std::set<std::string> paths;
    for (const auto& s : *secs) {
        SCOPED_TRACE(s.slideName + " / " + s.name);
        auto caps = rig_.station->journal().captures(s.id);
        ASSERT_TRUE(caps);
        ASSERT_EQ(caps->size(), 1u);
        paths.insert(caps->front().imagePath);
        // The file holds this section's own image: its name and its stage position.
        auto img = readOmeTiff(rig_.dir / caps->front().imagePath);
        ASSERT_TRUE(img) << img.error().message;
        EXPECT_EQ(img->info.name, "look-alike / " + s.slideName + " / " + s.name);
        EXPECT_NEAR(img->info.stage.xUm, s.xUm, 1.0);
        // The readable part is kept for people; the id makes the name unique.
        EXPECT_NE(caps->front().imagePath.find("/" + std::to_string(s.id) + "-"), std::string::npos)
            << caps->front().imagePath;
    }
    EXPECT_EQ(paths.size(), 5u) << "two captures share one file";
    EXPECT_EQ(imagesUnder(rig_.dir / "runs").size(), 5u);
    EXPECT_TRUE(alertsOf("storage_fault").empty());
}

TEST_F(StationTest, AFullDiskPausesTheRunOnceAndKeepsTheAlertUntilItCanBeStored) {
    auto& vfs = testing_vfs::FullDiskVfs::install();
    build("min_free_mb = 0\n");
    auto deliveredPtr = std::make_shared<DeliveredAlerts>();
    DeliveredAlerts& delivered = *deliveredPtr;
    rig_.station->notifier().addChannel(DeliveredAlerts::channel(deliveredPtr));
    auto id = rig_.station->submitPlan(planFor({0}), "plan");
    ASSERT_TRUE(id);
    // The disk fills once the run has started: the free-space check (0 >= 0 MB) lets it go on,
    // the image write fails with ENOSPC and the journal with SQLITE_FULL.
    rig_.freeBytes = 0;
    WriteFault enospc(ENOSPC);
    const JournalFillsOnceRunning fill(vfs, rig_.station->notifier());
    const int refusedBefore = vfs.refusedWrites();
    rig_.station->start();

    // The alert reaches the channels at once although it cannot be stored.
    ASSERT_TRUE(delivered.waitFor("run_paused"));
    EXPECT_EQ(delivered.count("low_disk"), 1u);
    EXPECT_GT(vfs.refusedWrites(), refusedBefore) << "the journal's writes were refused for real";
    auto run = rig_.station->journal().run(*id);
    ASSERT_TRUE(run);
    EXPECT_EQ(run->state, RunState::Running) << "the journal could not store the pause";
    // The alert goes out before the scanner holds the state it could not store: wait (bounded).
    auto heldStates = rig_.station->scanner().heldRunStates();
    for (const auto until = std::chrono::steady_clock::now() + 10s;
         heldStates.count(*id) == 0 && std::chrono::steady_clock::now() < until;
         heldStates = rig_.station->scanner().heldRunStates())
        std::this_thread::sleep_for(10ms); // polling the scanner's held states

    ASSERT_EQ(heldStates.count(*id), 1u);
    EXPECT_EQ(heldStates.at(*id), RunState::Paused);
    auto held = rig_.station->notifier().heldAlerts();
    ASSERT_EQ(held.size(), 2u);
    EXPECT_EQ(held[0].kind, AlertKind::LowDisk);
    EXPECT_LT(held[0].id, 0);
    EXPECT_EQ(held[1].kind, AlertKind::RunPaused);
    EXPECT_TRUE(imagesUnder(rig_.dir / "runs").empty());
    // The alert list (the API's and the page's) shows them already, open, with their ids.
    for (const bool openOnly : {true, false}) {
        auto listed = rig_.station->alerts(openOnly);
        ASSERT_TRUE(listed) << listed.error().message;
        ASSERT_GE(listed->size(), 2u);
        EXPECT_EQ((*listed)[listed->size() - 2].id, held[0].id);
        EXPECT_EQ(listed->back().id, held[1].id);
        EXPECT_EQ(listed->back().kind, AlertKind::RunPaused);
    }
    // Acknowledging one waits until it is stored: a clear refusal, nothing lost.
    auto ack = rig_.station->acknowledgeAlert(held[0].id, "accept");
    ASSERT_FALSE(ack);
    EXPECT_EQ(ack.error().code, core::ErrorCode::InvalidArgument);
    EXPECT_NE(ack.error().message.find("held in memory while the disk is full"), std::string::npos)
        << ack.error().message;

    // Paused in memory: the stage does not go back to the section. (Waiting for something not
    // to happen needs a time; the loop used to retry at once, many times a second.)
    const int moves = rig_.moves->load();
    std::this_thread::sleep_for(1500ms);
    EXPECT_EQ(rig_.moves->load(), moves) << "the scan loop went on retrying the section";
    EXPECT_EQ(delivered.count("low_disk"), 1u);
    EXPECT_EQ(rig_.station->notifier().heldAlerts().size(), 2u);

    // Space again: the pause and both alerts are stored, with their first raised time.
    enospc.clear();
    vfs.setFull(false);
    rig_.freeBytes = 100ull << 30;
    waitRun(*id, RunState::Paused);
    const auto deadline = std::chrono::steady_clock::now() + 30s;
    while (!rig_.station->notifier().heldAlerts().empty() &&
           std::chrono::steady_clock::now() < deadline)
        std::this_thread::sleep_for(50ms); // polling the notifier, bounded
    EXPECT_TRUE(rig_.station->notifier().heldAlerts().empty());
    auto lowDisk = alertsOf("low_disk");
    ASSERT_EQ(lowDisk.size(), 1u);
    EXPECT_EQ(lowDisk[0].raisedUtc, held[0].raisedUtc);
    EXPECT_FALSE(lowDisk[0].acknowledgedUtc.has_value());
    EXPECT_EQ(alertsOf("run_paused").size(), 1u);
    EXPECT_TRUE(rig_.station->scanner().heldRunStates().empty());

    ASSERT_TRUE(rig_.station->scanner().resume(*id));
    waitRun(*id, RunState::Finished);
    auto secs = rig_.station->journal().sections(*id);
    auto caps = rig_.station->journal().captures((*secs)[0].id);
    ASSERT_EQ(caps->size(), 1u);
    EXPECT_TRUE(readOmeTiff(rig_.dir / caps->front().imagePath));
}

TEST_F(StationTest, AFullJournalPausesTheRunAndTheImageItCouldNotRecordIsReplacedOnResume) {
    auto& vfs = testing_vfs::FullDiskVfs::install();
    build("autofocus = false\n");
    auto deliveredPtr = std::make_shared<DeliveredAlerts>();
    DeliveredAlerts& delivered = *deliveredPtr;
    rig_.station->notifier().addChannel(DeliveredAlerts::channel(deliveredPtr));
    auto id = rig_.station->submitPlan(planFor({1}), "plan");
    ASSERT_TRUE(id);
    const JournalFillsOnceRunning fill(vfs, rig_.station->notifier());
    rig_.station->start();
    ASSERT_TRUE(delivered.waitFor("run_paused"));
    EXPECT_EQ(delivered.count("low_disk"), 1u) << "SQLITE_FULL is a full disk, not a journal fault";
    EXPECT_EQ(delivered.count("journal_error"), 0u);
    // The image was written, the capture could not be recorded: no capture refers to the file.
    auto orphans = imagesUnder(rig_.dir / "runs");
    ASSERT_EQ(orphans.size(), 1u);

    vfs.setFull(false);
    waitRun(*id, RunState::Paused);
    // The alert held while the journal was full is stored by the notifier's own thread once the
    // journal takes writes again: wait for it (bounded) before counting the stored alerts.
    const auto deadline = std::chrono::steady_clock::now() + 30s;
    while (!rig_.station->notifier().heldAlerts().empty() &&
           std::chrono::steady_clock::now() < deadline)
        std::this_thread::sleep_for(50ms); // polling the notifier, bounded
    EXPECT_TRUE(rig_.station->notifier().heldAlerts().empty());
    EXPECT_EQ(alertsOf("low_disk").size(), 1u);
    ASSERT_TRUE(rig_.station->scanner().resume(*id));
    waitRun(*id, RunState::Finished);
    auto secs = rig_.station->journal().sections(*id);
    auto caps = rig_.station->journal().captures((*secs)[0].id);
    ASSERT_EQ(caps->size(), 1u);
    // The same name (attempt 1): the file no capture referred to was replaced, not refused.
    EXPECT_EQ(rig_.dir / caps->front().imagePath, orphans[0]);
    EXPECT_TRUE(readOmeTiff(orphans[0]));
    EXPECT_EQ(imagesUnder(rig_.dir / "runs").size(), 1u);
    EXPECT_TRUE(alertsOf("storage_fault").empty());
}

TEST_F(StationTest, AStageDisconnectDuringAutofocusIsAStageFault) {
    build();
    // The move to the section succeeds; the focus sweep's first move finds the stage gone.
    rig_.stage->disconnectAfter(1);
    auto id = rig_.station->submitPlan(planFor({0}), "plan");
    ASSERT_TRUE(id);
    rig_.station->start();
    const RunRecord paused = waitRun(*id, RunState::Paused);
    EXPECT_NE(paused.reason.find("stage_fault"), std::string::npos) << paused.reason;
    EXPECT_EQ(alertsOf("stage_fault").size(), 1u);
    EXPECT_TRUE(alertsOf("focus_fault").empty()) << "the advice would be about the camera";
    EXPECT_GE(rig_.moves->load(), 1);
}

TEST_F(StationTest, RestartRemovesTheTemporaryFilesOfEveryWriter) {
    namespace fs = std::filesystem;
    const fs::path slideDir = rig_.dir / "runs" / "1" / "01-slide-01";
    fs::create_directories(slideDir);
    fs::create_directories(rig_.dir / "atlas-builtin-100um");
    const std::vector<fs::path> leftovers = {
        slideDir / ".7-s1-a1.ome.tif.partial",                          // writeOmeTiffAtomic
        slideDir / ".7-s1-a1.overlay.png.tmp.4242.3.81234",             // core image writers
        rig_.dir / "atlas-builtin-100um" / ".slice-003.tif.tmp.17.0.5", // core, atlas stack
        slideDir / "7-s1-a1.result.json.tmp-4242",                      // writeFileAtomically
    };
    const std::vector<fs::path> kept = {
        slideDir / "7-s1-a1.ome.tif", slideDir / "7-s1-a1.overlay.png", slideDir / "tmp-notes.txt",
        slideDir / ".partial",        slideDir / "x.tmp-abc",           slideDir / ".a.tmp.1.2",
    };
    for (const auto& p : leftovers)
        std::ofstream(p) << "interrupted";
    for (const auto& p : kept)
        std::ofstream(p) << "data";
    build();
    for (const auto& p : leftovers)
        EXPECT_FALSE(fs::exists(p)) << p;
    for (const auto& p : kept)
        EXPECT_TRUE(fs::exists(p)) << p;
    EXPECT_TRUE(fs::exists(rig_.dir / "journal.sqlite"));
}

// The page's live stage position (issue 23 item 3): while the simulated stage travels (20 mm/s,
// a finite speed) the station publishes where it is, at most every 200 ms of stage time, then
// where the move ended; /api/status carries the last position seen.
TEST_F(StationTest, StagePositionsArePublishedDuringAMoveAtMostFiveTimesASecond) {
    build();
    // Shared with the listener, which outlives this body until TearDown stops the station.
    struct Seen {
        std::mutex m;
        std::vector<nlohmann::json> events;
        bool captured = false;
        std::condition_variable cv;
    };
    auto state = std::make_shared<Seen>();
    rig_.station->notifier().addListener([state](const StationEvent& e) {
        std::lock_guard lock(state->m);
        if (e.type == "stage_position")
            state->events.push_back(e.data);
        if (e.type == "section_captured")
            state->captured = true;
        state->cv.notify_all();
    });
    auto plan = planFor({0});
    auto id = rig_.station->submitPlan(plan, "plan");
    ASSERT_TRUE(id) << id.error().message;
    rig_.station->start();
    std::vector<nlohmann::json> events;
    {
        std::unique_lock lock(state->m);
        ASSERT_TRUE(state->cv.wait_for(lock, 60s, [&] { return state->captured; }));
        events = state->events;
    }
    (void)rig_.station->scanner().pause(*id);
    // The first move: from the start (0, 0) to the section, then where it ended.
    auto settled = std::find_if(events.begin(), events.end(),
                                [](const nlohmann::json& e) { return !e["moving"].get<bool>(); });
    ASSERT_NE(settled, events.end()) << "the end of the first move is published";
    const auto during = static_cast<std::size_t>(settled - events.begin());
    ASSERT_GE(during, 2u) << "positions arrive while the stage travels";
    const double endX = (*settled)["x_um"], endY = (*settled)["y_um"];
    EXPECT_NEAR(endX, plan["slides"][0]["sections"][0]["x_um"].get<double>(), 1.0);
    const double distanceUm = std::hypot(endX, endY);
    double lastX = -1;
    for (std::size_t k = 0; k < during; ++k) {
        const double x = events[k]["x_um"], y = events[k]["y_um"];
        EXPECT_TRUE(events[k]["moving"].get<bool>());
        EXPECT_GE(x, lastX) << "positions follow the travel";
        if (k > 0) { // strictly on the way: neither at the start nor at the end
            EXPECT_LT(std::hypot(x - endX, y - endY), distanceUm - 1.0) << k;
        }
        EXPECT_GT(std::hypot(x - endX, y - endY), 1.0) << k;
        lastX = x;
    }
    // 20 mm/s with 100 mm/s^2 ramps: the move lasts distance / speed + 0.2 s (+ settling; 0.4 s
    // allowed); at 5 Hz that is this many events (unthrottled, the 5 ms polls give 40 times more).
    const double seconds = distanceUm / 20'000.0 + 0.4;
    EXPECT_LE(static_cast<double>(during), seconds / 0.2 + 1.0)
        << during << " events over " << distanceUm << " um";
    std::cout << "stage_position: " << during << " events during a " << distanceUm
              << " um move (at most " << seconds << " s)\n";
    const nlohmann::json status = rig_.station->status();
    ASSERT_TRUE(status.contains("stage")) << status.dump();
    EXPECT_TRUE(status["stage"].contains("moving"));
}
