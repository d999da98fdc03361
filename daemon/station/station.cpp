#include "slicestation/daemon/station/station.hpp"

#include "slicestation/daemon/config/scan_plan.hpp"
#include "slicestation/daemon/storage/disk_space.hpp"
#include "slicestation/daemon/storage/temporary_files.hpp"

#include <iostream>
#include <sstream>

namespace slicestation::daemon {

namespace {

/// Reports every position the stage settled at (moves made by autofocus too), so a simulated
/// camera renders what lies under the objective, and every position seen during and after a move
/// to the station (the page's live position). Forwards everything else unchanged.
class ReportingStage final : public hw::Stage {
public:
    using Seen = std::function<void(const hw::StagePosition&,
                                    std::optional<std::chrono::steady_clock::time_point>)>;
    ReportingStage(std::unique_ptr<hw::Stage> inner,
                   std::function<void(const hw::StagePosition&)> settled, Seen seen)
        : inner_(std::move(inner)), settled_(std::move(settled)), seen_(std::move(seen)) {
        inner_->setMoveObserver([this](const hw::StagePosition& p,
                                       std::chrono::steady_clock::time_point at) { seen_(p, at); });
    }
    hw::StageLimits limits() const override { return inner_->limits(); }
    core::Result<hw::StagePosition> position(std::chrono::milliseconds t) override {
        return inner_->position(t);
    }
    core::Result<hw::StagePosition> moveTo(const hw::StagePosition& p,
                                           std::chrono::milliseconds t) override {
        return reported(inner_->moveTo(p, t));
    }
    core::Result<hw::StagePosition> home(std::chrono::milliseconds t) override {
        return reported(inner_->home(t));
    }
    void stop() noexcept override { inner_->stop(); }
    core::Result<hw::StageAlarm> alarm(std::chrono::milliseconds t) override {
        return inner_->alarm(t);
    }
    core::Result<void> resetAlarm(std::chrono::milliseconds t) override {
        return inner_->resetAlarm(t);
    }

private:
    core::Result<hw::StagePosition> reported(core::Result<hw::StagePosition> r) {
        if (r) {
            if (settled_)
                settled_(*r);
            seen_(*r, std::nullopt);
        }
        return r;
    }
    std::unique_ptr<hw::Stage> inner_;
    std::function<void(const hw::StagePosition&)> settled_;
    Seen seen_;
};

/// Hands every frame the camera delivers (autofocus frames too) to the live view.
class LiveCamera final : public hw::Camera {
public:
    LiveCamera(std::unique_ptr<hw::Camera> inner, std::function<void(const hw::Frame&)> seen)
        : inner_(std::move(inner)), seen_(std::move(seen)) {}
    core::Result<hw::CameraSettings> configure(const hw::CameraSettings& s,
                                               std::chrono::milliseconds t) override {
        return inner_->configure(s, t);
    }
    core::Result<hw::Frame> capture(std::chrono::milliseconds t) override {
        auto f = inner_->capture(t);
        if (f)
            seen_(*f);
        return f;
    }
    void stop() noexcept override { inner_->stop(); }

private:
    std::unique_ptr<hw::Camera> inner_;
    std::function<void(const hw::Frame&)> seen_;
};

} // namespace

using core::ErrorCode;
using core::makeError;
using core::Result;

Result<AtlasStack> openAtlasStack(const DaemonSettings& settings,
                                  const std::filesystem::path& stateDir) {
    if (settings.atlas != "builtin") {
        auto s = readStack(settings.atlas);
        if (!s)
            return makeError(s.error().code, "daemon.atlas: " + s.error().message);
        return s;
    }
    std::ostringstream name;
    name << "atlas-builtin-" << static_cast<int>(settings.builtinIntervalUm) << "um";
    const auto dir = stateDir / name.str();
    if (std::filesystem::exists(dir / "manifest.json")) {
        auto s = readStack(dir);
        if (s)
            return s;
        // A damaged copy of the built-in stack is rebuilt: it holds nothing of the user's.
        std::cerr << "<4>built-in atlas at " << dir << " unreadable (" << s.error().message
                  << "); writing it again" << std::endl;
    }
    auto slices = builtinStackSlices(settings.builtinIntervalUm, 0);
    if (!slices)
        return slices.error();
    return writeStack(
        dir, *slices, builtinStackRegions(),
        {{"kind", "builtin"}, {"plane", "coronal"}, {"interval_um", settings.builtinIntervalUm}});
}

Result<std::unique_ptr<Station>> Station::create(StationParts parts) {
    if (!parts.stage || !parts.camera)
        return makeError(ErrorCode::InvalidArgument, "station: a stage and a camera are required");
    std::error_code ec;
    std::filesystem::create_directories(parts.stateDir, ec);
    if (ec)
        return makeError(ErrorCode::IoError,
                         "state directory " + parts.stateDir.string() + ": " + ec.message(),
                         ec.value());
    if (!parts.freeSpace)
        parts.freeSpace = [](const std::filesystem::path& p) { return availableBytes(p); };
    std::unique_ptr<Station> st(new Station(std::move(parts)));
    {
        Station* self = st.get();
        st->parts_.stage = std::make_unique<ReportingStage>(
            std::move(st->parts_.stage), std::move(st->parts_.stageMoved),
            [self](const hw::StagePosition& p,
                   std::optional<std::chrono::steady_clock::time_point> at) {
                self->noteStagePosition(p, at);
            });
        st->parts_.stageMoved = nullptr;
        st->parts_.camera =
            std::make_unique<LiveCamera>(std::move(st->parts_.camera), [self](const hw::Frame& f) {
                auto copy = std::make_shared<const hw::Frame>(f); // ~2.6 MB for 1280x1024x16 bit
                std::lock_guard lock(self->liveMutex_);
                self->live_ = std::move(copy);
            });
    }
    auto journal = Journal::open(st->parts_.stateDir / "journal.sqlite");
    if (!journal)
        return journal.error();
    st->journal_ = std::move(*journal);
    st->notifier_ = std::make_unique<Notifier>(*st->journal_);
    for (auto& channel : st->parts_.alertChannels)
        st->notifier_->addChannel(std::move(channel));
    auto stack = openAtlasStack(st->parts_.settings, st->parts_.stateDir);
    if (!stack)
        return stack.error();
    st->stack_ = std::move(*stack);
    for (const auto& s : st->stack_.slices)
        st->slicePositionsUm_.push_back(s.positionUm);

    // Temporary files of writes a crash interrupted are never referenced: remove them (every
    // writer's naming scheme, anywhere in the state directory; nothing writes yet).
    if (auto removed = removeTemporaryFiles(st->parts_.stateDir); !removed)
        std::cerr << "<4>" << removed.error().message << std::endl;
    // A run left "running" means the daemon did not stop cleanly (crash, kill, watchdog).
    if (auto runs = st->journal_->runs()) {
        for (const auto& r : *runs)
            if (r.state == RunState::Running &&
                !std::filesystem::exists(st->parts_.stateDir / "clean-stop"))
                (void)st->notifier_->raise(
                    AlertKind::Restarted, AlertSeverity::Warning,
                    "the daemon restarted while run " + std::to_string(r.id) + " \"" + r.name +
                        "\" was in progress (crash, power cut or watchdog); resuming it",
                    r.id);
    }
    std::filesystem::remove(st->parts_.stateDir / "clean-stop", ec);

    st->worker_ = std::make_unique<RegistrationWorker>(*st->journal_, *st->notifier_, st->stack_,
                                                       st->parts_.stateDir, st->stats_);
    ScannerDeps deps{*st->parts_.stage,   *st->parts_.camera,   *st->journal_,
                     *st->notifier_,      *st->worker_,         st->stats_,
                     st->parts_.stateDir, st->parts_.freeSpace, st->parts_.watchdog,
                     st->parts_.status};
    st->scanner_ = std::make_unique<Scanner>(std::move(deps));
    return st;
}

void Station::noteStagePosition(const hw::StagePosition& p,
                                std::optional<std::chrono::steady_clock::time_point> at) {
    // At most one event per 200 ms of stage time while moving (5 Hz), and the settled position
    // once after a move that published one: a short autofocus step publishes nothing.
    constexpr auto kEvery = std::chrono::milliseconds(200);
    nlohmann::json ev;
    {
        std::lock_guard lock(stageMutex_);
        stage_ = p;
        stageMoving_ = at.has_value();
        if (at) {
            if (lastStageEvent_ && *at - *lastStageEvent_ < kEvery && *at >= *lastStageEvent_)
                return;
            lastStageEvent_ = at;
            stageAnnounced_ = true;
        } else {
            if (!stageAnnounced_)
                return;
            stageAnnounced_ = false;
        }
        ev = {{"x_um", p.xUm}, {"y_um", p.yUm}, {"z_um", p.zUm}, {"moving", at.has_value()}};
    }
    if (notifier_)
        notifier_->publish({"stage_position", ev});
}

Station::~Station() {
    stop();
}

void Station::start() {
    worker_->start();
    if (auto waiting = journal_->capturesAwaitingRegistration())
        for (auto id : *waiting)
            worker_->enqueue(id);
    scanner_->start();
}

void Station::stop() noexcept {
    if (!scanner_)
        return;
    scanner_->shutdown();
    worker_->stop();
    // Marks the stop as clean, so the next start raises no "restarted" alert.
    std::error_code ec;
    if (FILE* f = std::fopen((parts_.stateDir / "clean-stop").c_str(), "w"))
        std::fclose(f);
    (void)ec;
}

Result<std::int64_t> Station::submitPlan(const nlohmann::json& doc, const std::string& origin) {
    auto plan = parseScanPlan(doc, origin);
    if (!plan)
        return plan.error();
    if (auto r = resolveScanPlan(*plan, parts_.stage->limits(), slicePositionsUm_, origin); !r)
        return r.error();
    std::vector<PlannedSection> sections;
    for (const auto& ps : plan->sections)
        sections.push_back(ps.section);
    auto scan = settingsForNewRun();
    if (!scan)
        return scan.error();
    auto id = journal_->createRun(plan->name, plan->document, toJson(*scan), sections);
    if (!id)
        return id;
    notifier_->publish(
        {"run_state", {{"run_id", *id}, {"state", "queued"}, {"reason", "submitted"}}});
    scanner_->wake();
    return id;
}

Result<void> Station::requestRescan(std::int64_t sectionId) {
    auto r = journal_->requestRescan(sectionId);
    if (!r)
        return r;
    notifier_->publish({"section_rescan", {{"section_id", sectionId}}});
    scanner_->wake();
    return {};
}

Result<AlertRecord> Station::acknowledgeAlert(std::int64_t alertId, const std::string& action) {
    if (alertId < 0) // ids of alerts held in memory (Notifier)
        return makeError(ErrorCode::InvalidArgument,
                         "alert " + std::to_string(alertId) +
                             " is held in memory while the disk is full: it can be acknowledged "
                             "once it is stored");
    auto alert = journal_->alert(alertId);
    if (!alert)
        return alert.error();
    if (action == "rescan") {
        if (!alert->sectionId)
            return makeError(ErrorCode::InvalidArgument,
                             "alert " + std::to_string(alertId) + " concerns no section");
        if (auto r = requestRescan(*alert->sectionId); !r)
            return r.error();
    }
    return notifier_->acknowledge(alertId, action);
}

} // namespace slicestation::daemon
