#pragma once
// The station in one process for tests: simulated stage and camera over a virtual slide of four
// generated sections (the third torn), the built-in atlas, a real SQLite journal and real files
// in a temporary state directory. Shared by the station tests and the browser tests of the page.
#include "slicestation/daemon/config/config_document.hpp"
#include "slicestation/daemon/http/http_api.hpp"
#include "slicestation/daemon/station/station.hpp"
#include "slicestation/sim/faulty_camera.hpp"
#include "slicestation/sim/faulty_stage.hpp"
#include "slicestation/sim/sim_camera.hpp"
#include "slicestation/sim/sim_stage.hpp"
#include "slicestation/sim/virtual_slide.hpp"

#include "../common/test_dir.hpp"

#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <mutex>
#include <optional>
#include <thread>

namespace slicestation::testing_station {

using namespace slicestation::daemon;
using namespace std::chrono_literals;

inline constexpr double kUmPerPx = 10.0;
inline constexpr const char* kToken = "test-token-0123456789";

/// A slide of built-in sections at the atlas's physical size (the generator fills ~75% of the
/// patch; the built-in brain is ~9.7 mm wide, so 13 mm patches 14 mm apart), at kUmPerPx:
/// `sections` in grid cells of `columns`, in slide order. Throws when the generator refuses
/// the spec (a test's slide is fixed, so that is a mistake in the test).
inline sim::VirtualSlide builtinSlide(std::vector<sim::SlideSectionSpec> sections, int columns) {
    sim::VirtualSlideSpec spec;
    spec.columns = columns;
    spec.umPerPx = kUmPerPx;
    spec.sectionWidthUm = 13'000;
    spec.sectionPitchUm = 14'000;
    spec.sections = std::move(sections);
    auto r = sim::makeVirtualSlide(spec);
    if (!r)
        throw std::runtime_error(r.error().message);
    return *r;
}

/// Stage travel over a builtinSlide of one row of up to seven cells (the series tests' slides).
inline const hw::StageLimits kOneRowOfSevenLimits{
    {0, 110'000}, {0, 25'000}, hw::AxisRange{0, 5'000}};

/// Four sections in a row, the third torn; generated once for all tests.
inline const sim::VirtualSlide& slide() {
    static const sim::VirtualSlide s = [] {
        const double ap[] = {0.35, 0.45, 0.55, 0.65};
        std::vector<sim::SlideSectionSpec> sections;
        for (int i = 0; i < 4; ++i)
            sections.push_back({ap[i], i == 2 ? "tear" : "", static_cast<std::uint64_t>(100 + i)});
        return builtinSlide(std::move(sections), 4);
    }();
    return s;
}

/// One section of a plan: where the stage goes and the atlas slice the plan expects there.
struct PlanEntry {
    std::string name;
    double xUm = 0, yUm = 0;
    int slice = 0;
};

/// Section `i` of `onSlide` as the plans of the tests list it: "s<i+1>" at its centre.
inline PlanEntry entryOf(const sim::VirtualSlide& onSlide, int i, int slice) {
    const auto& s = onSlide.sections[static_cast<std::size_t>(i)];
    return {"s" + std::to_string(i + 1), s.centre.xUm, s.centre.yUm, slice};
}

/// A plan `name` of one slide, "slide-01", listing `planned` in order.
inline nlohmann::json planOf(const std::vector<PlanEntry>& planned,
                             const std::string& name = "test-run") {
    nlohmann::json secs = nlohmann::json::array();
    for (const PlanEntry& p : planned)
        secs.push_back(
            {{"name", p.name}, {"x_um", p.xUm}, {"y_um", p.yUm}, {"atlas_slice", p.slice}});
    return {{"name", name}, {"slides", {{{"name", "slide-01"}, {"sections", secs}}}}};
}

/// The plan for the slide: slice index = apFraction * 8000 um / 100 um.
inline nlohmann::json planFor(const std::vector<int>& which, const std::string& name = "test-run") {
    std::vector<PlanEntry> planned;
    for (int i : which) {
        const double ap = slide().sections[static_cast<std::size_t>(i)].apFraction;
        planned.push_back(entryOf(slide(), i, static_cast<int>(std::lround(ap * 80))));
    }
    return planOf(planned, name);
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
    std::shared_ptr<std::atomic<int>> moves =
        std::make_shared<std::atomic<int>>(0); ///< stage moves done
};

class StationTest : public ::testing::Test {
protected:
    void SetUp() override {
        rig_.dir = testing_dir::perTestPath("station"); // the station makes it
        std::filesystem::remove_all(rig_.dir);
    }
    void TearDown() override {
        if (rig_.api)
            rig_.api->stop();
        if (rig_.station)
            rig_.station->stop();
        rig_.station.reset();
        std::filesystem::remove_all(rig_.dir);
    }

    /// Builds the station (not started). `scanToml` overrides [scan] keys.
    void build(const std::string& scanExtra = "") {
        sim::SimStageConfig sc;
        sc.clock = std::make_shared<core::VirtualClock>(); // moves complete at once
        sc.start = {0, 0, 2'500};
        if (stageLimits_)
            sc.limits = *stageLimits_;
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
        auto simCamera = sim::SimCamera::create(*slide_, cc);
        ASSERT_TRUE(simCamera) << simCamera.error().message;
        auto camera = sim::FaultyCamera::create(std::move(*simCamera),
                                                std::make_shared<core::VirtualClock>());
        ASSERT_TRUE(camera);
        rig_.camera = camera->get();

        auto doc =
            parseDocument(std::string("[daemon]\ntoken = \"") + kToken + "\"\n" + daemonExtra_ +
                              "[scan]\num_per_px = " + std::to_string(kUmPerPx) +
                              "\nwidth = 1280\nheight = 1024\n" + scanExtra,
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
        parts.freeSpace = [freeBytes](const std::filesystem::path&) -> core::Result<std::uint64_t> {
            return *freeBytes;
        };
        auto moves = rig_.moves;
        parts.stageMoved = [pos, mu, moves](const hw::StagePosition& p) {
            ++*moves;
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
            if (!r)
                return {};
            if (r->state == state && (state != RunState::Finished || rig_.station->idle()))
                return *r;
            if (std::chrono::steady_clock::now() > deadline) {
                ADD_FAILURE() << "run " << id << " is " << toString(r->state) << " (" << r->reason
                              << "), expected " << toString(state);
                return *r;
            }
            std::this_thread::sleep_for(50ms); // polling the journal, not waiting for time to pass
        }
    }

    /// Submits `plan`, starts the station and waits (bounded, waitRun) until the run is
    /// finished. \return the run; a refused plan is a test failure and gives id 0.
    RunRecord runToTheEnd(const nlohmann::json& plan) {
        auto id = rig_.station->submitPlan(plan, "plan");
        EXPECT_TRUE(id) << id.error().message;
        if (!id)
            return {};
        rig_.station->start();
        return waitRun(*id, RunState::Finished);
    }

    std::vector<AlertRecord> alertsOf(const std::string& kind) {
        std::vector<AlertRecord> out;
        auto all = rig_.station->journal().alerts(false);
        EXPECT_TRUE(all);
        if (!all)
            return out;
        for (const auto& a : *all)
            if (toString(a.kind) == kind)
                out.push_back(a);
        return out;
    }

    Rig rig_;
    /// What the camera sees and how far the stage goes; set before build().
    const sim::VirtualSlide* slide_ = &slide();
    std::optional<hw::StageLimits> stageLimits_;
    /// More [daemon] keys, one per line (e.g. `atlas = "DIR"\n`); set before build().
    std::string daemonExtra_;
};

} // namespace slicestation::testing_station
