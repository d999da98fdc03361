#include "slicestation/daemon/station/scanner.hpp"

#include "slicestation/daemon/station/autofocus.hpp"
#include "slicestation/daemon/storage/ome_tiff.hpp"
#include "slicestation/daemon/service/systemd_notifier.hpp"
#include "slicestation/daemon/station/tile_stitcher.hpp"

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <map>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using core::Result;

namespace {

/// Why a section could not be captured: the alert kind and the error.
struct Fault {
    std::string kind; ///< stage_fault, camera_fault, focus_fault, low_disk, storage_fault
    core::Error error;
};

/// The readable part of a file name: ASCII letters, digits, '-' and '_' kept, every other byte
/// '_', at most kMaxNamePart bytes. Not injective ("s/1" and "s_1" both give "s_1"): the path
/// adds the journal's ids for that (imagePathFor).
constexpr std::size_t kMaxNamePart = 48;
std::string safeName(const std::string& s) {
    std::string out;
    for (char c : s) {
        if (out.size() == kMaxNamePart) break;
        const auto u = static_cast<unsigned char>(c);
        out += (u < 0x80 && (std::isalnum(u) || c == '-' || c == '_')) ? c : '_';
    }
    return out.empty() ? std::string("_") : out;
}

/// Where a capture's image goes, relative to the state directory:
///   runs/<run id>/<slide number, 2+ digits>-<slide name>/<section id>-<section name>-a<attempt>.ome.tif
/// The run id, slide number (index + 1 within the run) and section id (unique in the journal)
/// make it injective whatever the names; the names are only there for people.
std::filesystem::path imagePathFor(const RunRecord& run, const SectionRecord& sec, int attempt) {
    char slide[16];
    std::snprintf(slide, sizeof slide, "%02d", sec.slideIndex + 1);
    return std::filesystem::path("runs") / std::to_string(run.id) /
           (std::string(slide) + "-" + safeName(sec.slideName)) /
           (std::to_string(sec.id) + "-" + safeName(sec.name) + "-a" + std::to_string(attempt) + ".ome.tif");
}

/// The frame's pixels as a Mat (copied; RGB becomes OpenCV's BGR).
cv::Mat toMat(const hw::Frame& f) {
    switch (f.format()) {
    case hw::PixelFormat::Mono8:
        return cv::Mat(f.height(), f.width(), CV_8UC1, const_cast<std::uint8_t*>(f.bytes().data()), f.stride()).clone();
    case hw::PixelFormat::Mono16:
        return cv::Mat(f.height(), f.width(), CV_16UC1, const_cast<std::uint8_t*>(f.bytes().data()), f.stride()).clone();
    case hw::PixelFormat::Rgb8: {
        cv::Mat rgb(f.height(), f.width(), CV_8UC3, const_cast<std::uint8_t*>(f.bytes().data()), f.stride());
        cv::Mat bgr;
        cv::cvtColor(rgb, bgr, cv::COLOR_RGB2BGR);
        return bgr;
    }
    }
    return {};
}

/// Camera-to-stage orientation: camera axes lie along stage axes (a signed permutation, checked
/// by the settings), so turning a frame into the stage frame is a transpose and/or flips.
struct Orientation {
    bool transpose = false, flipX = false, flipY = false;
};
Orientation orientation(const std::array<double, 4>& m) {
    Orientation o;
    double a = m[0], d = m[3];
    if (std::abs(m[0]) < 0.5) { // axes swapped: after a transpose the matrix is [b a; d c]
        o.transpose = true;
        a = m[1];
        d = m[2];
    }
    o.flipX = a < 0;
    o.flipY = d < 0;
    return o;
}
cv::Mat orient(const cv::Mat& m, const Orientation& o) {
    cv::Mat out = m;
    if (o.transpose) cv::transpose(out, out);
    if (o.flipX && o.flipY) cv::flip(out, out, -1);
    else if (o.flipX) cv::flip(out, out, 1);
    else if (o.flipY) cv::flip(out, out, 0);
    return out;
}

} // namespace

Scanner::Scanner(ScannerDeps deps) : d_(std::move(deps)) {}

Scanner::~Scanner() { shutdown(); }

void Scanner::start() {
    std::lock_guard lock(mutex_);
    if (thread_.joinable()) return;
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
    if (thread_.joinable()) thread_.join();
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
    if (!run) return run.error();
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
        return makeError(ErrorCode::InvalidArgument,
                         "run " + std::to_string(runId) + " is " + toString(run->state) + "; it cannot be paused");
    settle(runId, RunState::Paused, "paused by request");
    return {};
}

core::Result<void> Scanner::resume(std::int64_t runId, bool resetStageAlarm) {
    auto run = d_.journal.run(runId);
    if (!run) return run.error();
    RunState state = run->state;
    {
        std::lock_guard lock(mutex_);
        if (auto h = held_.find(runId); h != held_.end()) state = h->second.state; // paused in memory
    }
    if (state != RunState::Paused)
        return makeError(ErrorCode::InvalidArgument,
                         "run " + std::to_string(runId) + " is " + toString(state) + ", not paused");
    {
        std::lock_guard lock(mutex_);
        pauseRequested_.erase(runId);
        if (resetStageAlarm) alarmResetRequested_.insert(runId);
    }
    auto r = d_.journal.setRunState(runId, RunState::Queued,
                                    resetStageAlarm ? "resumed, stage alarm reset asked" : "resumed");
    if (!r) return r; // a run paused in memory stays so
    {
        std::lock_guard lock(mutex_);
        held_.erase(runId);
    }
    d_.notifier.publish({"run_state", {{"run_id", runId}, {"state", "queued"}, {"reason", "resumed"}}});
    wake();
    return {};
}

core::Result<void> Scanner::cancel(std::int64_t runId) {
    auto run = d_.journal.run(runId);
    if (!run) return run.error();
    {
        std::lock_guard lock(mutex_);
        if (auto h = held_.find(runId); h != held_.end()) run->state = h->second.state;
    }
    if (isTerminal(run->state) && run->state != RunState::Finished)
        return makeError(ErrorCode::InvalidArgument,
                         "run " + std::to_string(runId) + " is already " + toString(run->state));
    if (run->state == RunState::Finished)
        return makeError(ErrorCode::InvalidArgument, "run " + std::to_string(runId) + " has finished");
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
    for (const auto& [id, h] : held_) out.emplace(id, h.state);
    return out;
}

void Scanner::settle(std::int64_t runId, RunState state, const std::string& reason) {
    if (d_.notifier.runStateChanged(runId, state, reason)) return;
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
        if (it == held_.end()) return true;
        h = it->second;
        if (!d_.journal.setRunState(runId, h.state, h.reason)) return false;
        held_.erase(it);
    }
    d_.notifier.publish({"run_state", {{"run_id", runId}, {"state", toString(h.state)}, {"reason", h.reason}}});
    return true;
}

void Scanner::setActivity(const std::string& text) {
    {
        std::lock_guard lock(mutex_);
        activity_ = text;
    }
    if (d_.status) d_.status(text);
    if (d_.watchdog) d_.watchdog->progress();
}

void Scanner::loop() {
    while (!shutdown_) {
        (void)d_.notifier.storeHeldAlerts(); // alerts a full disk kept out of the journal
        auto next = d_.journal.nextRun();
        if (!next) {
            (void)d_.notifier.raise("journal_error", "critical",
                                    "cannot read the journal: " + next.error().message);
            std::unique_lock lock(mutex_);
            cv_.wait_for(lock, std::chrono::seconds(5), [this] { return wake_ || shutdown_.load(); });
            wake_ = false;
            continue;
        }
        if (!*next) {
            {
                std::lock_guard lock(mutex_);
                idle_ = true;
                activity_ = "idle";
            }
            if (d_.status) d_.status("idle: no run queued");
            if (d_.watchdog) d_.watchdog->setIdle(true);
            std::unique_lock lock(mutex_);
            cv_.wait_for(lock, std::chrono::seconds(1), [this] { return wake_ || shutdown_.load(); });
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
            if (storeHeldState((*next)->id)) continue;
            const std::string what = "run " + std::to_string((*next)->id) +
                                     " paused; the journal cannot store it yet (disk full?)";
            {
                std::lock_guard lock(mutex_);
                activity_ = what;
            }
            if (d_.status) d_.status(what);
            if (d_.watchdog) d_.watchdog->setIdle(true);
            std::unique_lock lock(mutex_);
            cv_.wait_for(lock, std::chrono::seconds(1), [this] { return wake_ || shutdown_.load(); });
            wake_ = false;
            continue;
        }
        if (d_.watchdog) d_.watchdog->setIdle(false);
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

Scanner::Outcome Scanner::executeRun(const RunRecord& run) {
    const std::string runLabel = "run " + std::to_string(run.id);
    auto settings = scanSettingsFromJson(run.settings, runLabel + " settings");
    if (!settings) {
        settle(run.id, RunState::Failed, settings.error().message);
        return Outcome::Failed;
    }
    const ScanSettings& s = *settings;
    auto pauseFor = [&](const Fault& f) {
        // A full disk, whoever found it (image writer: ENOSPC, journal: SQLITE_FULL).
        const std::string kind = f.error.sysErrno == ENOSPC ? std::string("low_disk") : f.kind;
        (void)d_.notifier.raise(kind, "critical", runLabel + ": " + f.error.message, run.id);
        settle(run.id, RunState::Paused, kind + ": " + f.error.message);
        return Outcome::Paused;
    };
    if (run.state == RunState::Queued) {
        if (auto r = d_.journal.setRunState(run.id, RunState::Running); !r)
            return pauseFor({"journal_error", r.error()});
        d_.notifier.publish({"run_state", {{"run_id", run.id}, {"state", "running"}, {"reason", ""}}});
    }

    bool resetAlarm = false;
    {
        std::lock_guard lock(mutex_);
        resetAlarm = alarmResetRequested_.erase(run.id) > 0;
    }
    if (resetAlarm) {
        setActivity(runLabel + ": resetting the stage alarm");
        if (auto r = d_.stage.resetAlarm(s.moveTimeout); !r) {
            if (shutdown_) return Outcome::Shutdown;
            return pauseFor({"stage_fault", r.error()});
        }
    }

    // The run's own camera settings (snapshot), read back from the device.
    hw::CameraSettings used;
    {
        setActivity(runLabel + ": configuring the camera");
        Result<hw::CameraSettings> c = d_.camera.configure(s.camera, s.captureTimeout);
        for (int attempt = 0; !c && attempt < s.captureRetries && !shutdown_; ++attempt)
            c = d_.camera.configure(s.camera, s.captureTimeout);
        if (!c) {
            if (shutdown_) return Outcome::Shutdown;
            return pauseFor({"camera_fault", c.error()});
        }
        used = *c;
    }
    const Orientation orient0 = orientation(s.objective.cameraToStage);
    const double um = s.objective.umPerPx;
    const double fieldWUm = (orient0.transpose ? used.height : used.width) * um;
    const double fieldHUm = (orient0.transpose ? used.width : used.height) * um;

    // Focus surfaces per slide, rebuilt from what this run already focused (resume starts close).
    std::map<int, FocusSurface> surfaces;
    int total = 0;
    if (auto secs = d_.journal.sections(run.id)) {
        total = static_cast<int>(secs->size());
        for (const auto& sec : *secs)
            if (auto caps = d_.journal.captures(sec.id))
                for (const auto& c : *caps)
                    if (c.focusFound) surfaces[sec.slideIndex].add(c.stage.xUm, c.stage.yUm, c.stage.zUm);
    }

    const hw::StageLimits limits = d_.stage.limits();
    auto moveTo = [&](hw::StagePosition target) -> Result<hw::StagePosition> {
        PhaseTimer t(d_.stats, "move");
        if (!limits.z) target.zUm = 0;
        Result<hw::StagePosition> r = d_.stage.moveTo(target, s.moveTimeout);
        for (int attempt = 0; attempt < s.moveRetries && !r; ++attempt) {
            const auto code = r.error().code;
            if (code == ErrorCode::Cancelled || code == ErrorCode::OutOfRange || code == ErrorCode::Alarm)
                break;
            r = d_.stage.moveTo(target, s.moveTimeout);
        }
        if (r && d_.stageMoved) d_.stageMoved(*r);
        if (r && d_.watchdog) d_.watchdog->progress();
        return r;
    };
    auto capture = [&]() -> Result<hw::Frame> {
        PhaseTimer t(d_.stats, "capture");
        Result<hw::Frame> r = d_.camera.capture(s.captureTimeout);
        for (int attempt = 0; attempt < s.captureRetries && !r; ++attempt) {
            if (r.error().code == ErrorCode::Cancelled) break;
            // Re-initialise before trying again (a camera that timed out often needs it).
            d_.camera.stop();
            if (auto c = d_.camera.configure(s.camera, s.captureTimeout); !c) {
                r = c.error();
                continue;
            }
            r = d_.camera.capture(s.captureTimeout);
        }
        if (r && d_.watchdog) d_.watchdog->progress();
        return r;
    };

    for (;;) {
        if (shutdown_) return Outcome::Shutdown;
        {
            std::unique_lock lock(mutex_);
            if (cancelRequested_.count(run.id)) {
                lock.unlock();
                settle(run.id, RunState::Cancelled, "cancelled by request");
                return Outcome::Cancelled;
            }
            if (pauseRequested_.count(run.id)) {
                pauseRequested_.erase(run.id);
                lock.unlock();
                settle(run.id, RunState::Paused, "paused by request");
                return Outcome::Paused;
            }
        }
        auto next = d_.journal.nextSectionToCapture(run.id);
        if (!next) return pauseFor({"journal_error", next.error()});
        if (!*next) {
            // Everything captured: the run is finished once the worker has registered it all.
            auto secs = d_.journal.sections(run.id);
            if (!secs) return pauseFor({"journal_error", secs.error()});
            const bool pending = std::any_of(secs->begin(), secs->end(), [](const SectionRecord& x) {
                return x.state == SectionState::Captured;
            });
            if (pending) {
                setActivity(runLabel + ": waiting for registrations");
                d_.worker.waitIdle(std::chrono::milliseconds(200));
                if (d_.worker.idle()) {
                    // Idle but still 'captured' (e.g. after a restart): queue them again.
                    if (auto waiting = d_.journal.capturesAwaitingRegistration())
                        for (auto id : *waiting) d_.worker.enqueue(id);
                    d_.worker.waitIdle(std::chrono::milliseconds(200));
                }
                continue;
            }
            settle(run.id, RunState::Finished, "");
            return Outcome::Done;
        }
        const SectionRecord sec = **next;
        const std::string where = runLabel + " " + sec.slideName + " section " + sec.name + " (" +
                                  std::to_string(sec.slideIndex + 1) + "/" + std::to_string(sec.index + 1) +
                                  " of " + std::to_string(total) + ")";

        // Disk first: never start a section we cannot store.
        if (d_.freeSpace) {
            auto free = d_.freeSpace(d_.stateDir);
            if (!free) return pauseFor({"storage_fault", free.error()});
            if (*free < s.minFreeBytes)
                return pauseFor({"low_disk", makeError(ErrorCode::IoError,
                                                       "low disk: " + std::to_string(*free >> 20) +
                                                           " MB free in " + d_.stateDir.string() +
                                                           ", the threshold is " +
                                                           std::to_string(s.minFreeBytes >> 20) + " MB")});
        }

        auto handle = [&](const core::Error& e, const char* kind) {
            if (e.code == ErrorCode::Cancelled) {
                if (shutdown_) return Outcome::Shutdown;
                std::unique_lock lock(mutex_);
                if (cancelRequested_.count(run.id)) {
                    lock.unlock();
                    settle(run.id, RunState::Cancelled, "cancelled by request");
                    return Outcome::Cancelled;
                }
            }
            return pauseFor({kind, e});
        };

        // Move to the section at the predicted focus.
        double z = s.startZUm;
        if (auto p = surfaces[sec.slideIndex].predict(sec.xUm, sec.yUm)) z = *p;
        if (limits.z) z = std::clamp(z, limits.z->minUm, limits.z->maxUm);
        setActivity(where + ": moving");
        auto moved = moveTo({sec.xUm, sec.yUm, z});
        if (!moved) return handle(moved.error(), "stage_fault");

        // Autofocus at the centre (a tissue check first: never focus on blank glass).
        bool focusFound = false;
        std::optional<double> focusScore;
        if (s.autofocus && limits.z) {
            setActivity(where + ": focusing");
            PhaseTimer t(d_.stats, "focus");
            AutofocusSettings afs;
            afs.rangeUm = s.focusRangeUm;
            afs.coarseStepUm = s.focusCoarseStepUm;
            afs.fineStepUm = s.focusFineStepUm;
            afs.minTissueFraction = s.minTissueFraction;
            afs.moveTimeout = s.moveTimeout;
            afs.captureTimeout = s.captureTimeout;
            afs.moveRetries = s.moveRetries;
            afs.captureRetries = s.captureRetries;
            FocusFailure failed = FocusFailure::Focus;
            auto af = autofocus(d_.stage, d_.camera, {sec.xUm, sec.yUm, z}, afs, &failed);
            // A stage that failed (alarm, disconnect, a move that timed out after its retries)
            // is not helped by focusing again; a camera or focus failure gets one more try.
            if (!af && af.error().code != ErrorCode::Cancelled && failed != FocusFailure::Stage)
                af = autofocus(d_.stage, d_.camera, {sec.xUm, sec.yUm, z}, afs, &failed);
            // A stage error during the focus sweep is a stage fault like any other, a capture
            // error a camera fault; only the search itself failing is a focus fault.
            if (!af)
                return handle(af.error(), failed == FocusFailure::Stage    ? "stage_fault"
                                          : failed == FocusFailure::Camera ? "camera_fault"
                                                                           : "focus_fault");
            if (af->tissueFound) {
                z = af->zUm;
                focusFound = true;
                focusScore = af->score;
                surfaces[sec.slideIndex].add(sec.xUm, sec.yUm, z);
            }
        }

        // Capture: one field, or tiles stitched by stage position.
        setActivity(where + ": capturing");
        const TilePlan tilePlan = planTiles({sec.xUm, sec.yUm, z}, sec.widthUm, sec.heightUm, fieldWUm,
                                            fieldHUm, s.tileOverlap);
        std::vector<Tile> tiles;
        hw::FrameMetadata meta;
        hw::StagePosition centreStage{sec.xUm, sec.yUm, z};
        for (const auto& c : tilePlan.centres) {
            auto at = moveTo({c.xUm, c.yUm, z});
            if (!at) return handle(at.error(), "stage_fault");
            auto frame = capture();
            if (!frame) return handle(frame.error(), "camera_fault");
            meta = frame->metadata;
            if (tilePlan.centres.size() == 1) centreStage = *at;
            tiles.push_back({orient(toMat(*frame), orient0), *at});
        }
        cv::Mat image;
        if (tiles.size() == 1) {
            image = tiles.front().image;
        } else {
            setActivity(where + ": stitching " + std::to_string(tiles.size()) + " tiles");
            PhaseTimer t(d_.stats, "stitch");
            auto st = stitchTiles(tiles, um);
            if (!st) return handle(st.error(), "camera_fault");
            image = *st;
        }

        // Write the image atomically, then journal it, then hand it on.
        setActivity(where + ": writing");
        const int attempt = sec.attempts + 1;
        const std::filesystem::path rel = imagePathFor(run, sec, attempt);
        {
            PhaseTimer t(d_.stats, "write");
            std::error_code ec;
            std::filesystem::create_directories((d_.stateDir / rel).parent_path(), ec);
            if (ec)
                return pauseFor({"storage_fault", makeError(ErrorCode::IoError,
                                                            "cannot create " + (d_.stateDir / rel).parent_path().string() +
                                                                ": " + ec.message(), ec.value())});
            OmeTiffInfo info;
            info.umPerPx = um;
            info.stage = centreStage;
            info.channel = used.format == hw::PixelFormat::Rgb8 ? "brightfield" : "fluorescence";
            info.name = run.name + " / " + sec.slideName + " / " + sec.name;
            info.exposureUs = meta.exposureUs;
            info.gain = meta.analogueGain;
            info.acquiredUtc = Journal::nowUtc();
            auto w = writeOmeTiffAtomic(d_.stateDir / rel, image, info);
            if (!w && w.error().sysErrno == EEXIST) {
                // The writer never replaces a file. One no capture refers to was written by a
                // run a crash interrupted before it was journaled: it may go. One a capture
                // refers to is never overwritten.
                auto owner = d_.journal.captureWithImage(rel.string());
                if (!owner) return pauseFor({"journal_error", owner.error()});
                if (*owner)
                    return pauseFor({"storage_fault",
                                     makeError(ErrorCode::IoError,
                                               (d_.stateDir / rel).string() + " is the image of capture " +
                                                   std::to_string(**owner) + "; it is not overwritten",
                                               EEXIST)});
                std::error_code removeEc;
                std::filesystem::remove(d_.stateDir / rel, removeEc);
                w = writeOmeTiffAtomic(d_.stateDir / rel, image, info);
            }
            if (!w) return pauseFor({w.error().sysErrno == ENOSPC ? "low_disk" : "storage_fault", w.error()});
        }
        CaptureRecord rec;
        rec.sectionId = sec.id;
        rec.imagePath = rel.string();
        rec.umPerPx = um;
        rec.stage = centreStage;
        rec.focusFound = focusFound;
        rec.focusScore = focusScore;
        rec.tiles = static_cast<int>(tiles.size());
        rec.exposureUs = meta.exposureUs;
        rec.gain = meta.analogueGain;
        auto id = d_.journal.recordCapture(rec);
        if (!id) return pauseFor({"journal_error", id.error()});
        rec.id = *id;
        rec.attempt = attempt;
        nlohmann::json ev = toJson(rec);
        ev["run_id"] = run.id;
        ev["section"] = sec.name;
        d_.notifier.publish({"section_captured", ev});
        d_.worker.enqueue(*id);
    }
}

} // namespace slicestation::daemon
