// slst_bench_overnight: an accelerated overnight run through the whole station in one process.
// 8 slides x 24 sections (by default) on a simulated stage with real travel and settle times and
// a simulated camera over a virtual slide of generated sections (every 7th torn), the built-in
// atlas, a real journal and real files, with faults injected on a schedule: camera timeouts and
// move timeouts that the retries absorb, and a drive alarm that pauses the run until a
// "technician" resets it and resumes. Prints sections per hour, time per phase, peak memory, and
// lost or duplicated sections (must be zero).
#include "slicestation/daemon/config/config_document.hpp"
#include "slicestation/daemon/station/station.hpp"
#include "slicestation/sim/sim_camera.hpp"
#include "slicestation/sim/sim_stage.hpp"
#include "slicestation/sim/virtual_slide.hpp"

#include <CLI/CLI.hpp>

#include <sys/resource.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <iostream>
#include <map>
#include <mutex>
#include <thread>

using namespace slicestation;
using namespace slicestation::daemon;
using namespace std::chrono_literals;

namespace {

/// Faults on a schedule, by call count, thread-safe to configure up front.
class ScheduledStage final : public hw::Stage {
public:
    ScheduledStage(std::unique_ptr<hw::Stage> inner, int timeoutEvery, int alarmAtMove)
        : inner_(std::move(inner)), timeoutEvery_(timeoutEvery), alarmAtMove_(alarmAtMove) {}
    hw::StageLimits limits() const override { return inner_->limits(); }
    core::Result<hw::StagePosition> position(std::chrono::milliseconds t) override {
        return inner_->position(t);
    }
    core::Result<hw::StagePosition> moveTo(const hw::StagePosition& p,
                                           std::chrono::milliseconds t) override {
        const int n = ++moves_;
        if (alarmLatched_)
            return core::makeError(core::ErrorCode::Alarm, "axis x: alarm 0x30 (overload)");
        if (n == alarmAtMove_) {
            alarmLatched_ = true;
            ++alarms;
            return core::makeError(core::ErrorCode::Alarm, "axis x: alarm 0x30 (overload)");
        }
        if (timeoutEvery_ > 0 && n % timeoutEvery_ == 0) {
            ++timeouts;
            return core::makeError(core::ErrorCode::Timeout,
                                   "axis y: not in position before the deadline");
        }
        return inner_->moveTo(p, t);
    }
    core::Result<hw::StagePosition> home(std::chrono::milliseconds t) override {
        return inner_->home(t);
    }
    void stop() noexcept override { inner_->stop(); }
    core::Result<hw::StageAlarm> alarm(std::chrono::milliseconds t) override {
        return inner_->alarm(t);
    }
    core::Result<void> resetAlarm(std::chrono::milliseconds) override {
        alarmLatched_ = false;
        return {};
    }
    std::atomic<int> timeouts{0}, alarms{0};

private:
    std::unique_ptr<hw::Stage> inner_;
    int timeoutEvery_, alarmAtMove_;
    std::atomic<int> moves_{0};
    std::atomic<bool> alarmLatched_{false};
};

class ScheduledCamera final : public hw::Camera {
public:
    ScheduledCamera(std::unique_ptr<hw::Camera> inner, int timeoutEvery)
        : inner_(std::move(inner)), timeoutEvery_(timeoutEvery) {}
    core::Result<hw::CameraSettings> configure(const hw::CameraSettings& s,
                                               std::chrono::milliseconds t) override {
        return inner_->configure(s, t);
    }
    core::Result<hw::Frame> capture(std::chrono::milliseconds t) override {
        if (timeoutEvery_ > 0 && ++captures_ % timeoutEvery_ == 0) {
            ++timeouts;
            return core::makeError(core::ErrorCode::Timeout,
                                   "camera: no frame before the deadline");
        }
        return inner_->capture(t);
    }
    void stop() noexcept override { inner_->stop(); }
    std::atomic<int> timeouts{0};

private:
    std::unique_ptr<hw::Camera> inner_;
    int timeoutEvery_;
    std::atomic<int> captures_{0};
};

} // namespace

int main(int argc, char** argv) {
    CLI::App app{"slst_bench_overnight: an accelerated overnight run through the station"};
    int slides = 8, perSlide = 24;
    std::string stateDir = "/tmp/slst-overnight";
    double speedUmPerS = 50'000;
    app.add_option("--slides", slides, "Slides in the run");
    app.add_option("--sections", perSlide, "Sections per slide");
    app.add_option("--state-dir", stateDir, "State directory (emptied first)");
    app.add_option("--speed-um-per-s", speedUmPerS,
                   "Stage speed (simulated travel takes real time)");
    CLI11_PARSE(app, argc, argv);

    std::filesystem::remove_all(stateDir);
    const auto t0 = std::chrono::steady_clock::now();
    // One slide of `perSlide` sections in 6 columns; every slide of the run shows the same glass
    // (a slide loader swaps them), so the slide image is generated once.
    sim::VirtualSlideSpec spec;
    // Tissue at the atlas's physical size (the generator fills ~75% of the patch; the built-in
    // brain is ~9.7 mm wide), so the configured pixel size means what it says.
    spec.columns = 6;
    spec.sectionPitchUm = 14'000;
    spec.sectionWidthUm = 13'000;
    spec.umPerPx = 10;
    for (int i = 0; i < perSlide; ++i)
        spec.sections.push_back({0.1 + 0.8 * i / std::max(1, perSlide - 1),
                                 i % 7 == 3 ? "tear" : "", static_cast<std::uint64_t>(1000 + i)});
    auto slide = sim::makeVirtualSlide(spec);
    if (!slide) {
        std::cerr << "virtual slide: " << slide.error().message << "\n";
        return 1;
    }
    const double genS =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();

    sim::SimStageConfig sc;
    sc.limits = {{0, 120'000}, {0, 80'000}, hw::AxisRange{0, 5'000}};
    sc.start = {0, 0, 2'500};
    sc.speedUmPerS = speedUmPerS;
    sc.accelUmPerS2 = speedUmPerS * 5;
    sc.settle = 20ms;
    auto simStage = sim::SimStage::create(sc);
    if (!simStage)
        return 1;
    const int totalMoves = slides * perSlide * 14; // about a move per focus step and one per field
    auto stage = std::make_unique<ScheduledStage>(std::move(*simStage), 97, totalMoves / 2);
    ScheduledStage* stagePtr = stage.get();
    auto pos = std::make_shared<std::pair<std::mutex, hw::StagePosition>>();
    sim::SimCameraConfig cc;
    cc.sensorUmPerPx = 10;
    cc.stagePosition = [pos] {
        std::lock_guard lock(pos->first);
        return pos->second;
    };
    auto simCamera = sim::SimCamera::create(*slide, cc);
    if (!simCamera) {
        std::cerr << simCamera.error().message << "\n";
        return 1;
    }
    auto camera = std::make_unique<ScheduledCamera>(std::move(*simCamera), 131);
    ScheduledCamera* cameraPtr = camera.get();

    auto doc =
        parseDocument("[daemon]\ntoken = \"bench-token-0123456789\"\n[scan]\num_per_px = 10\n"
                      "width = 1280\nheight = 1024\n"
                      // the built-in atlas only supports matching to ~10 slices
                      "atlas_mismatch_tolerance = 12\n",
                      DocumentFormat::Toml, "bench");
    auto settings = parseDaemonSettings(*doc, "bench");
    if (!settings) {
        std::cerr << settings.error().message << "\n";
        return 1;
    }
    StationParts parts;
    parts.stage = std::move(stage);
    parts.camera = std::move(camera);
    parts.simulatedStage = parts.simulatedCamera = true;
    parts.settings = *settings;
    parts.stateDir = stateDir;
    parts.stageMoved = [pos](const hw::StagePosition& p) {
        std::lock_guard lock(pos->first);
        pos->second = p;
    };
    auto st = Station::create(std::move(parts));
    if (!st) {
        std::cerr << st.error().message << "\n";
        return 1;
    }
    Station& station = **st;

    nlohmann::json plan{{"name", "overnight"}, {"slides", nlohmann::json::array()}};
    for (int s = 0; s < slides; ++s) {
        nlohmann::json secs = nlohmann::json::array();
        for (const auto& sec : slide->sections)
            secs.push_back({{"x_um", sec.centre.xUm},
                            {"y_um", sec.centre.yUm},
                            {"atlas_slice", static_cast<int>(std::lround(sec.apFraction * 80))}});
        plan["slides"].push_back({{"name", "slide-" + std::to_string(s + 1)}, {"sections", secs}});
    }
    auto runId = station.submitPlan(plan, "bench plan");
    if (!runId) {
        std::cerr << runId.error().message << "\n";
        return 1;
    }
    const auto tRun = std::chrono::steady_clock::now();
    station.start();
    double pausedS = 0;
    int resumes = 0;
    for (;;) {
        std::this_thread::sleep_for(200ms);
        auto r = station.journal().run(*runId);
        if (!r)
            return 1;
        if (r->state == RunState::Finished && station.idle())
            break;
        if (r->state == RunState::Paused) {
            // The technician answers the alert: reset the drive's alarm, resume.
            const auto tp = std::chrono::steady_clock::now();
            (void)stagePtr->resetAlarm(1s);
            if (!station.scanner().resume(*runId))
                return 1;
            ++resumes;
            pausedS += std::chrono::duration<double>(std::chrono::steady_clock::now() - tp).count();
        }
        if (isTerminal(r->state) && r->state != RunState::Finished) {
            std::cerr << "run ended " << toString(r->state) << ": " << r->reason << "\n";
            return 1;
        }
    }
    const double runS =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - tRun).count();
    station.stop();

    // Completeness: every planned section captured exactly once, registered, files on disk.
    int lost = 0, duplicated = 0, damaged = 0, damagedAndTorn = 0, missingFiles = 0, total = 0;
    auto secs = station.journal().sections(*runId);
    for (const auto& s : *secs) {
        ++total;
        auto caps = station.journal().captures(s.id);
        if (caps->empty() ||
            (s.state != SectionState::Registered && s.state != SectionState::Damaged))
            ++lost;
        if (caps->size() > 1)
            ++duplicated;
        for (const auto& c : *caps)
            if (!std::filesystem::exists(std::filesystem::path(stateDir) / c.imagePath))
                ++missingFiles;
        if (s.state == SectionState::Damaged) {
            ++damaged;
            if (s.index % 7 == 3)
                ++damagedAndTorn; // the painted ones (see the slide above)
        }
    }
    const bool integrity = static_cast<bool>(station.journal().checkIntegrity());
    std::map<std::string, int> alertKinds;
    if (auto alerts = station.journal().alerts(false))
        for (const auto& a : *alerts)
            ++alertKinds[toString(a.kind)];
    rusage ru{};
    getrusage(RUSAGE_SELF, &ru);
    const auto phases = station.stats().summary();

    std::printf("overnight run: %d slides x %d sections = %d sections (slide generation %.1f s, "
                "not counted)\n",
                slides, perSlide, total, genS);
    std::printf("| metric | value |\n|---|---|\n");
    std::printf("| run wall time | %.1f s |\n", runS);
    std::printf("| sections per hour | %.0f |\n", total / runS * 3600.0);
    std::printf(
        "| lost sections | %d |\n| duplicated captures | %d |\n| images missing on disk | %d |\n",
        lost, duplicated, missingFiles);
    std::printf("| flagged damaged | %d, of which painted torn %d (painted torn: %d) |\n", damaged,
                damagedAndTorn, slides * ((perSlide + 3) / 7));
    std::printf("| injected: move timeouts / camera timeouts / alarms | %d / %d / %d |\n",
                stagePtr->timeouts.load(), cameraPtr->timeouts.load(), stagePtr->alarms.load());
    std::printf("| pauses answered (alarm) | %d |\n", resumes);
    std::printf("| journal integrity | %s |\n", integrity ? "ok" : "FAILED");
    std::string kinds;
    for (const auto& [k, n] : alertKinds)
        kinds += (kinds.empty() ? "" : ", ") + k + " " + std::to_string(n);
    std::printf("| alerts raised | %s |\n", kinds.c_str());
    std::printf("| peak memory (max RSS) | %.0f MB |\n", ru.ru_maxrss / 1024.0);
    std::printf("\n| phase | count | mean ms | median ms | max ms | total s "
                "|\n|---|---|---|---|---|---|\n");
    for (const auto& [name, p] : phases.items())
        std::printf("| %s | %d | %.1f | %.1f | %.1f | %.1f |\n", name.c_str(),
                    p["count"].get<int>(), p["mean_ms"].get<double>(), p["median_ms"].get<double>(),
                    p["max_ms"].get<double>(), p["total_s"].get<double>());
    (void)pausedS;
    return lost == 0 && duplicated == 0 && missingFiles == 0 && integrity ? 0 : 1;
}
