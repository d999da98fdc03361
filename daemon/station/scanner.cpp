#include "slicestation/daemon/station/scanner.hpp"

#include "slicestation/daemon/service/systemd_notifier.hpp"
#include "slicestation/daemon/station/autofocus.hpp"

#include <algorithm>
#include <cerrno>
#include <map>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using core::Result;

Scanner::Scanner(ScannerDeps deps) : d_(std::move(deps)) {}

Scanner::~Scanner() {
    shutdown();
}

void Scanner::start() {
    std::lock_guard lock(mutex_);
    if (thread_.joinable())
        return;
    thread_ = std::thread([this] { loop(); });
}

void Scanner::shutdown() noexcept {
    shutdown_ = true;
    d_.stage.stop();
    d_.camera.stop();
    {
        std::lock_guard lock(mutex_);
        wake_ = true;
    }
    cv_.notify_all();
    if (thread_.joinable())
        thread_.join();
}

void Scanner::wake() {
    {
        std::lock_guard lock(mutex_);
        wake_ = true;
        idle_ = false;
    }
    cv_.notify_all();
}

core::Result<void> Scanner::pause(std::int64_t runId) {
    auto run = d_.journal.run(runId);
    if (!run)
        return run.error();
    std::unique_lock lock(mutex_);
    if (active_ == runId) {
        pauseRequested_.insert(runId);
        return {};
    }
    if (held_.count(runId))
        return makeError(ErrorCode::InvalidArgument, "run " + std::to_string(runId) + " is " +
                                                         toString(held_.at(runId).state) +
                                                         " (not yet stored: the disk is full)");
    lock.unlock();
    if (run->state != RunState::Queued && run->state != RunState::Running)
        return makeError(ErrorCode::InvalidArgument, "run " + std::to_string(runId) + " is " +
                                                         toString(run->state) +
                                                         "; it cannot be paused");
    settle(runId, RunState::Paused, "paused by request");
    return {};
}

core::Result<void> Scanner::resume(std::int64_t runId, bool resetStageAlarm) {
    auto run = d_.journal.run(runId);
    if (!run)
        return run.error();
    RunState state = run->state;
    {
        std::lock_guard lock(mutex_);
        if (auto h = held_.find(runId); h != held_.end())
            state = h->second.state; // paused in memory
    }
    if (state != RunState::Paused)
        return makeError(ErrorCode::InvalidArgument, "run " + std::to_string(runId) + " is " +
                                                         toString(state) + ", not paused");
    {
        std::lock_guard lock(mutex_);
        pauseRequested_.erase(runId);
        if (resetStageAlarm)
            alarmResetRequested_.insert(runId);
    }
    auto r = d_.journal.setRunState(
        runId, RunState::Queued, resetStageAlarm ? "resumed, stage alarm reset asked" : "resumed");
    if (!r)
        return r; // a run paused in memory stays so
    {
        std::lock_guard lock(mutex_);
        held_.erase(runId);
    }
    d_.notifier.publish(
        {"run_state", {{"run_id", runId}, {"state", "queued"}, {"reason", "resumed"}}});
    wake();
    return {};
}

core::Result<void> Scanner::cancel(std::int64_t runId) {
    auto run = d_.journal.run(runId);
    if (!run)
        return run.error();
    {
        std::lock_guard lock(mutex_);
        if (auto h = held_.find(runId); h != held_.end())
            run->state = h->second.state;
    }
    if (isTerminal(run->state) && run->state != RunState::Finished)
        return makeError(ErrorCode::InvalidArgument,
                         "run " + std::to_string(runId) + " is already " + toString(run->state));
    if (run->state == RunState::Finished)
        return makeError(ErrorCode::InvalidArgument,
                         "run " + std::to_string(runId) + " has finished");
    std::unique_lock lock(mutex_);
    if (active_ == runId) {
        cancelRequested_.insert(runId);
        lock.unlock();
        // Preempt the move or capture in progress; the loop sees the request and cancels.
        d_.stage.stop();
        d_.camera.stop();
        cv_.notify_all();
        return {};
    }
    lock.unlock();
    auto r = d_.notifier.runStateChanged(runId, RunState::Cancelled, "cancelled by request");
    if (r) {
        std::lock_guard relock(mutex_);
        held_.erase(runId);
    }
    return r;
}

std::optional<std::int64_t> Scanner::activeRun() const {
    std::lock_guard lock(mutex_);
    return active_;
}

std::string Scanner::activity() const {
    std::lock_guard lock(mutex_);
    return activity_;
}

bool Scanner::idle() const {
    std::lock_guard lock(mutex_);
    return idle_ && d_.worker.idle();
}

std::map<std::int64_t, RunState> Scanner::heldRunStates() const {
    std::lock_guard lock(mutex_);
    std::map<std::int64_t, RunState> out;
    for (const auto& [id, h] : held_)
        out.emplace(id, h.state);
    return out;
}

void Scanner::settle(std::int64_t runId, RunState state, const std::string& reason) {
    if (d_.notifier.runStateChanged(runId, state, reason))
        return;
    // The alert went out (and is held until it can be stored); the state is kept here so the
    // loop does not take the run up again, and stored as soon as the journal can.
    std::lock_guard lock(mutex_);
    held_[runId] = {state, reason};
}

bool Scanner::storeHeldState(std::int64_t runId) {
    HeldState h;
    {
        // Locked across the write: once the journal shows the state, it is no longer held.
        std::lock_guard lock(mutex_);
        auto it = held_.find(runId);
        if (it == held_.end())
            return true;
        h = it->second;
        if (!d_.journal.setRunState(runId, h.state, h.reason))
            return false;
        held_.erase(it);
    }
    d_.notifier.publish(
        {"run_state", {{"run_id", runId}, {"state", toString(h.state)}, {"reason", h.reason}}});
    return true;
}

void Scanner::setActivity(const std::string& text) {
    {
        std::lock_guard lock(mutex_);
        activity_ = text;
    }
    if (d_.status)
        d_.status(text);
    if (d_.watchdog)
        d_.watchdog->progress();
}

void Scanner::loop() {
    while (!shutdown_) {
        (void)d_.notifier.storeHeldAlerts(); // alerts a full disk kept out of the journal
        auto next = d_.journal.nextRun();
        if (!next) {
            (void)d_.notifier.raise(AlertKind::JournalError, AlertSeverity::Critical,
                                    "cannot read the journal: " + next.error().message);
            std::unique_lock lock(mutex_);
            cv_.wait_for(lock, std::chrono::seconds(5),
                         [this] { return wake_ || shutdown_.load(); });
            wake_ = false;
            continue;
        }
        if (!*next) {
            {
                std::lock_guard lock(mutex_);
                idle_ = true;
                activity_ = "idle";
            }
            if (d_.status)
                d_.status("idle: no run queued");
            if (d_.watchdog)
                d_.watchdog->setIdle(true);
            std::unique_lock lock(mutex_);
            cv_.wait_for(lock, std::chrono::seconds(1),
                         [this] { return wake_ || shutdown_.load(); });
            wake_ = false;
            continue;
        }
        bool held = false;
        {
            std::lock_guard lock(mutex_);
            held = held_.count((*next)->id) > 0;
        }
        if (held) {
            // Paused (or ended) in memory: the journal could not store it. Never take it up
            // again; store the state once there is space.
            if (storeHeldState((*next)->id))
                continue;
            const std::string what = "run " + std::to_string((*next)->id) +
                                     " paused; the journal cannot store it yet (disk full?)";
            {
                std::lock_guard lock(mutex_);
                activity_ = what;
            }
            if (d_.status)
                d_.status(what);
            if (d_.watchdog)
                d_.watchdog->setIdle(true);
            std::unique_lock lock(mutex_);
            cv_.wait_for(lock, std::chrono::seconds(1),
                         [this] { return wake_ || shutdown_.load(); });
            wake_ = false;
            continue;
        }
        if (d_.watchdog)
            d_.watchdog->setIdle(false);
        {
            std::lock_guard lock(mutex_);
            idle_ = false;
            active_ = (*next)->id;
        }
        executeRun(**next);
        std::lock_guard lock(mutex_);
        active_.reset();
        pauseRequested_.erase((*next)->id);
        cancelRequested_.erase((*next)->id);
    }
}

/// What one run's sections share: its settings snapshot, the camera settings in use, the focus
/// surfaces per slide, and the steps over the devices.
struct Scanner::RunContext {
    const RunRecord& run;
    std::string label; ///< "run <id>"
    ScanSettings settings;
    hw::CameraSettings used;
    std::map<int, FocusSurface> surfaces; ///< per slide index
    int total = 0;                        ///< sections in the run
};

Scanner::Outcome Scanner::executeRun(const RunRecord& run) {
    const std::string label = "run " + std::to_string(run.id);
    auto settings = scanSettingsFromJson(run.settings, label + " settings");
    if (!settings) {
        settle(run.id, RunState::Failed, settings.error().message);
        return Outcome::Failed;
    }
    RunContext ctx{run, label, *settings, {}, {}, 0};
    SectionSteps steps({d_.stage, d_.camera, d_.stats, d_.stateDir, d_.freeSpace, d_.watchdog},
                       ctx.settings);
    if (auto o = startRun(ctx, steps))
        return *o;
    for (;;) {
        if (shutdown_)
            return Outcome::Shutdown;
        if (auto o = takeRequest(run.id))
            return *o;
        auto next = d_.journal.nextSectionToCapture(run.id);
        if (!next)
            return pauseFor(ctx, {AlertKind::JournalError, next.error()});
        if (!*next) {
            if (auto o = finishOnceRegistered(ctx))
                return *o;
            continue;
        }
        if (auto o = scanSection(ctx, steps, **next))
            return *o;
    }
}

Scanner::Outcome Scanner::pauseFor(const RunContext& ctx, const Fault& f) {
    // A full disk, whoever found it (image writer: ENOSPC, journal: SQLITE_FULL).
    const AlertKind kind = f.error.sysErrno == ENOSPC ? AlertKind::LowDisk : f.kind;
    (void)d_.notifier.raise(kind, AlertSeverity::Critical, ctx.label + ": " + f.error.message,
                            ctx.run.id);
    settle(ctx.run.id, RunState::Paused, toString(kind) + (": " + f.error.message));
    return Outcome::Paused;
}

Scanner::Outcome Scanner::onFault(const RunContext& ctx, const Fault& f) {
    if (f.error.code == ErrorCode::Cancelled) {
        // stop() preempted the device: a shutdown, or a cancel of this run.
        if (shutdown_)
            return Outcome::Shutdown;
        std::unique_lock lock(mutex_);
        if (cancelRequested_.count(ctx.run.id)) {
            lock.unlock();
            settle(ctx.run.id, RunState::Cancelled, "cancelled by request");
            return Outcome::Cancelled;
        }
    }
    return pauseFor(ctx, f);
}

std::optional<Scanner::Outcome> Scanner::startRun(RunContext& ctx, SectionSteps& steps) {
    const RunRecord& run = ctx.run;
    if (run.state == RunState::Queued) {
        if (auto r = d_.journal.setRunState(run.id, RunState::Running); !r)
            return pauseFor(ctx, {AlertKind::JournalError, r.error()});
        d_.notifier.publish(
            {"run_state", {{"run_id", run.id}, {"state", "running"}, {"reason", ""}}});
    }
    bool resetAlarm = false;
    {
        std::lock_guard lock(mutex_);
        resetAlarm = alarmResetRequested_.erase(run.id) > 0;
    }
    if (resetAlarm) {
        setActivity(ctx.label + ": resetting the stage alarm");
        if (auto r = d_.stage.resetAlarm(ctx.settings.moveTimeout); !r) {
            if (shutdown_)
                return Outcome::Shutdown;
            return pauseFor(ctx, {AlertKind::StageFault, r.error()});
        }
    }
    // The run's own camera settings (snapshot), read back from the device.
    setActivity(ctx.label + ": configuring the camera");
    auto used = steps.configureCamera();
    if (!used) {
        if (shutdown_)
            return Outcome::Shutdown;
        return pauseFor(ctx, used.fault());
    }
    ctx.used = *used;
    // Focus surfaces per slide, rebuilt from what this run already focused (resume starts close).
    if (auto secs = d_.journal.sections(run.id)) {
        ctx.total = static_cast<int>(secs->size());
        for (const auto& sec : *secs)
            if (auto caps = d_.journal.captures(sec.id))
                for (const auto& c : *caps)
                    if (c.focusFound)
                        ctx.surfaces[sec.slideIndex].add(c.stage.xUm, c.stage.yUm, c.stage.zUm);
    }
    return std::nullopt;
}

std::optional<Scanner::Outcome> Scanner::takeRequest(std::int64_t runId) {
    std::unique_lock lock(mutex_);
    if (cancelRequested_.count(runId)) {
        lock.unlock();
        settle(runId, RunState::Cancelled, "cancelled by request");
        return Outcome::Cancelled;
    }
    if (pauseRequested_.count(runId)) {
        pauseRequested_.erase(runId);
        lock.unlock();
        settle(runId, RunState::Paused, "paused by request");
        return Outcome::Paused;
    }
    return std::nullopt;
}

std::optional<Scanner::Outcome> Scanner::finishOnceRegistered(const RunContext& ctx) {
    // Everything captured: the run is finished once the worker has registered it all.
    auto secs = d_.journal.sections(ctx.run.id);
    if (!secs)
        return pauseFor(ctx, {AlertKind::JournalError, secs.error()});
    const bool pending = std::any_of(secs->begin(), secs->end(), [](const SectionRecord& x) {
        return x.state == SectionState::Captured;
    });
    if (!pending) {
        settle(ctx.run.id, RunState::Finished, "");
        return Outcome::Done;
    }
    setActivity(ctx.label + ": waiting for registrations");
    d_.worker.waitIdle(std::chrono::milliseconds(200));
    if (d_.worker.idle()) {
        // Idle but still 'captured' (e.g. after a restart): queue them again.
        if (auto waiting = d_.journal.capturesAwaitingRegistration())
            for (auto id : *waiting)
                d_.worker.enqueue(id);
        d_.worker.waitIdle(std::chrono::milliseconds(200));
    }
    return std::nullopt;
}

std::optional<Scanner::Outcome> Scanner::scanSection(RunContext& ctx, SectionSteps& steps,
                                                     const SectionRecord& sec) {
    const std::string where = ctx.label + " " + sec.slideName + " section " + sec.name + " (" +
                              std::to_string(sec.slideIndex + 1) + "/" +
                              std::to_string(sec.index + 1) + " of " + std::to_string(ctx.total) +
                              ")";
    if (auto f = steps.checkDisk())
        return pauseFor(ctx, *f);

    // Move to the section at the predicted focus.
    const ScanSettings& s = ctx.settings;
    const auto zLimits = d_.stage.limits().z;
    double z = s.startZUm;
    if (auto p = ctx.surfaces[sec.slideIndex].predict(sec.xUm, sec.yUm))
        z = *p;
    if (zLimits)
        z = std::clamp(z, zLimits->minUm, zLimits->maxUm);
    setActivity(where + ": moving");
    if (auto moved = steps.move({sec.xUm, sec.yUm, z}); !moved)
        return onFault(ctx, moved.fault());

    // Autofocus at the centre (a tissue check first: never focus on blank glass).
    if (s.autofocus && zLimits)
        setActivity(where + ": focusing");
    auto focus = steps.focus(sec.xUm, sec.yUm, z);
    if (!focus)
        return onFault(ctx, focus.fault());
    if (focus->found)
        ctx.surfaces[sec.slideIndex].add(sec.xUm, sec.yUm, focus->zUm);

    // Capture: one field, or tiles stitched by stage position.
    setActivity(where + ": capturing");
    auto captured = steps.capture(
        sec, focus->zUm, [&](const std::string& what) { setActivity(where + ": " + what); });
    if (!captured)
        return onFault(ctx, captured.fault());

    // Write the image atomically, then journal it, then hand it on.
    setActivity(where + ": writing");
    const int attempt = sec.attempts + 1;
    const std::filesystem::path rel = imagePathFor(ctx.run, sec, attempt);
    if (auto f = steps.writeImage(rel, *captured,
                                  ctx.run.name + " / " + sec.slideName + " / " + sec.name, ctx.used,
                                  d_.journal))
        return pauseFor(ctx, *f);
    CaptureRecord rec;
    rec.sectionId = sec.id;
    rec.imagePath = rel.string();
    rec.umPerPx = s.objective.umPerPx;
    rec.stage = captured->stage;
    rec.focusFound = focus->found;
    rec.focusScore = focus->score;
    rec.tiles = captured->tiles;
    rec.exposureUs = captured->meta.exposureUs;
    rec.gain = captured->meta.analogueGain;
    auto id = d_.journal.recordCapture(rec);
    if (!id)
        return pauseFor(ctx, {AlertKind::JournalError, id.error()});
    rec.id = *id;
    rec.attempt = attempt;
    nlohmann::json ev = toJson(rec);
    ev["run_id"] = ctx.run.id;
    ev["section"] = sec.name;
    d_.notifier.publish({"section_captured", ev});
    d_.worker.enqueue(*id);
    return std::nullopt;
}

} // namespace slicestation::daemon
