// Cells per region in the daemon (docs/cells.md): with scan.count_cells the registration worker
// writes COUNTS.csv and CELLS.csv beside each result and the run's totals, and the API serves
// them; without it nothing is counted and the API says so.
#include "station_fixture.hpp"

#include "slicestation/core/csv.hpp"

#include <gtest/gtest.h>
#include <httplib.h>

#include <condition_variable>
#include <filesystem>
#include <mutex>

using namespace slicestation;
using namespace slicestation::daemon;
using namespace slicestation::testing_station;

TEST_F(StationTest, CountsCellsAfterRegistrationWhenAskedAndServesThem) {
    // 30 um at the simulated 10 um/px: 3 px blobs.
    build("count_cells = true\ncell_diameter_um = 30\n");
    auto api = HttpApi::start(*rig_.station, "127.0.0.1", 0, kToken);
    ASSERT_TRUE(api) << api.error().message;
    rig_.api = std::move(*api);
    // Counting follows the journaled registration on the worker: wait for its events.
    std::mutex mu;
    std::condition_variable cv;
    int counted = 0;
    std::vector<std::string> failures;
    rig_.station->addListener([&](const StationEvent& e) {
        if (e.type != "cells_counted" && e.type != "cells_count_failed")
            return;
        std::lock_guard lock(mu);
        ++counted;
        if (e.type == "cells_count_failed")
            failures.push_back(e.data.dump());
        cv.notify_all();
    });
    auto id = rig_.station->submitPlan(planFor({0, 1}), "plan");
    ASSERT_TRUE(id) << id.error().message;
    rig_.station->start();
    waitRun(*id, RunState::Finished);
    {
        std::unique_lock lock(mu);
        ASSERT_TRUE(cv.wait_for(lock, std::chrono::seconds(120), [&] { return counted >= 2; }));
        EXPECT_TRUE(failures.empty()) << failures.front();
    }

    auto secs = rig_.station->journal().sections(*id);
    ASSERT_TRUE(secs);
    httplib::Client cli("127.0.0.1", rig_.api->port());
    for (const auto& s : *secs) {
        SCOPED_TRACE(s.name);
        auto regs = rig_.station->journal().registrations(s.id);
        ASSERT_EQ(regs->size(), 1u);
        std::string base = regs->front().resultPath;
        base = base.substr(0, base.size() - std::string(".result.json").size());
        EXPECT_TRUE(std::filesystem::exists(rig_.dir / (base + ".counts.csv")));
        EXPECT_TRUE(std::filesystem::exists(rig_.dir / (base + ".cells.csv")));
        auto res = cli.Get("/api/sections/" + std::to_string(s.id) + "/counts");
        ASSERT_TRUE(res);
        EXPECT_EQ(res->status, 200);
        EXPECT_EQ(res->body.rfind("id,acronym,name,parent_id,depth,count,area_mm2", 0), 0u)
            << res->body.substr(0, 200);
        auto recs = core::parseCsv(res->body, "counts");
        ASSERT_TRUE(recs);
        EXPECT_GT(recs->size(), 2u) << "regions of the built-in atlas with tissue";
    }
    auto run = cli.Get("/api/runs/" + std::to_string(*id) + "/counts");
    ASSERT_TRUE(run);
    EXPECT_EQ(run->status, 200);
    EXPECT_EQ(run->body.rfind("id,acronym", 0), 0u);
    EXPECT_TRUE(
        std::filesystem::exists(rig_.dir / "runs" / std::to_string(*id) / "run-counts.csv"));
    EXPECT_EQ(cli.Get("/api/runs/999/counts")->status, 404);
}

TEST_F(StationTest, CountsNothingUnlessAsked) {
    build();
    auto api = HttpApi::start(*rig_.station, "127.0.0.1", 0, kToken);
    ASSERT_TRUE(api) << api.error().message;
    rig_.api = std::move(*api);
    auto id = rig_.station->submitPlan(planFor({0}), "plan");
    ASSERT_TRUE(id) << id.error().message;
    rig_.station->start();
    waitRun(*id, RunState::Finished);
    auto secs = rig_.station->journal().sections(*id);
    ASSERT_TRUE(secs);
    httplib::Client cli("127.0.0.1", rig_.api->port());
    auto res = cli.Get("/api/sections/" + std::to_string(secs->front().id) + "/counts");
    ASSERT_TRUE(res);
    EXPECT_EQ(res->status, 404);
    EXPECT_FALSE(
        std::filesystem::exists(rig_.dir / "runs" / std::to_string(*id) / "run-counts.csv"));
}
