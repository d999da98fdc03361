#pragma once
/// The scan loop: one thread that owns the stage and the camera and works through the journal's
/// runs in order. Per section: check the disk, move, settle, autofocus (coarse to fine, never on
/// blank glass, starting from the slide's focus surface), capture (tiles when the section is
/// larger than the field of view, stitched), write the OME-TIFF atomically, journal it, and
/// hand it to the registration worker — the stage moves on at once.
///
/// Faults follow one policy (retry_policy.hpp): moves, captures and the camera's configuration
/// are retried a bounded number of times (a camera is re-initialised between capture attempts);
/// then, and at once for a drive alarm or a low disk, the run
/// is paused with the reason and an alert. Nothing is skipped silently. A full disk (ENOSPC from
/// the image writer, SQLITE_FULL from the journal) pauses the run with a `low_disk` alert; when
/// the journal cannot store the pause either, the run is paused in memory (heldRunStates();
/// likewise a finished, failed or cancelled state the journal refused): the loop does not work
/// on it, retries storing the state about once a second (and the held alerts,
/// Notifier::storeHeldAlerts), and once stored the run is paused like any other. resume() and
/// cancel() act on a run paused in memory as on a paused one.
///
/// Control (from any thread): pause/resume/cancel take effect between sections; cancel and
/// shutdown also preempt a move or capture in progress (stage/camera stop()). Shutdown leaves
/// the run "running" so a restarted daemon resumes it.
#include "slicestation/core/camera.hpp"
#include "slicestation/core/stage.hpp"
#include "slicestation/daemon/alerts/notifier.hpp"
#include "slicestation/daemon/config/daemon_settings.hpp"
#include "slicestation/daemon/station/phase_stats.hpp"
#include "slicestation/daemon/station/registration_worker.hpp"
#include "slicestation/daemon/station/section_steps.hpp"
#include "slicestation/daemon/storage/journal.hpp"

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <thread>

namespace slicestation::daemon {

class ProgressWatchdog;

struct ScannerDeps {
    hw::Stage& stage;
    hw::Camera& camera;
    Journal& journal;
    Notifier& notifier;
    RegistrationWorker& worker;
    PhaseStats& stats;
    std::filesystem::path stateDir;
    /// Free bytes where images are written (availableBytes; tests inject a full disk).
    std::function<core::Result<std::uint64_t>(const std::filesystem::path&)> freeSpace;
    /// Progress and STATUS= for systemd; may be null.
    ProgressWatchdog* watchdog = nullptr;
    std::function<void(const std::string&)> status;
};

class Scanner {
public:
    explicit Scanner(ScannerDeps deps);
    ~Scanner();
    Scanner(const Scanner&) = delete;
    Scanner& operator=(const Scanner&) = delete;

    void start();
    /// Stops the stage, finishes the current transaction and joins. The run stays "running".
    void shutdown() noexcept;

    /// Wake the loop (a plan was submitted, a run resumed, a rescan requested).
    void wake();
    /// Pause/cancel a run: at once for a run not in progress, between sections (cancel also
    /// preempts) for the one in progress. Errors: NotFound, InvalidArgument (wrong state).
    core::Result<void> pause(std::int64_t runId);
    /// `resetStageAlarm`: the technician has cleared the cause of a stage alarm; the scan loop
    /// (the stage's owning thread) resets the drives' alarm before the run goes on. Alarms are
    /// never reset unless asked.
    core::Result<void> resume(std::int64_t runId, bool resetStageAlarm = false);
    core::Result<void> cancel(std::int64_t runId);

    /// The run in progress, if any.
    std::optional<std::int64_t> activeRun() const;
    /// What the loop is doing now, e.g. "run 3 slide 2/8 section 5/24: focusing".
    std::string activity() const;
    /// No run to work on and the registration worker idle.
    bool idle() const;
    /// Runs whose new state (paused, or finished/failed/cancelled) the journal could not store
    /// yet (disk full), with that state; the journal still shows them running or queued.
    std::map<std::int64_t, RunState> heldRunStates() const;

private:
    void loop();
    enum class Outcome { Done, Paused, Cancelled, Shutdown, Failed };
    struct RunContext;
    /// One run: startRun(), then per section takeRequest() and scanSection() (the steps of
    /// section_steps.hpp), until finishOnceRegistered() or a fault.
    Outcome executeRun(const RunRecord& run);
    /// Running, the stage alarm reset when asked, the camera configured, the focus surfaces
    /// rebuilt. nullopt: go on.
    std::optional<Outcome> startRun(RunContext& ctx, SectionSteps& steps);
    /// A pause or cancel asked for this run, taken between sections.
    std::optional<Outcome> takeRequest(std::int64_t runId);
    /// Every section captured: Done once all are registered; nullopt while waiting.
    std::optional<Outcome> finishOnceRegistered(const RunContext& ctx);
    /// Disk, move, focus, capture, write, journal, hand to the worker. nullopt: captured.
    std::optional<Outcome> scanSection(RunContext& ctx, SectionSteps& steps,
                                       const SectionRecord& section);
    /// The run paused with the fault's alert (low_disk for any ENOSPC).
    Outcome pauseFor(const RunContext& ctx, const Fault& fault);
    /// As pauseFor, but a Cancelled device call ends the run as cancelled (or shuts down).
    Outcome onFault(const RunContext& ctx, const Fault& fault);
    void setActivity(const std::string& text);
    /// Journals the run's new state (with its alert); when the journal cannot, holds it in
    /// memory (the loop then leaves the run alone).
    void settle(std::int64_t runId, RunState state, const std::string& reason);
    /// Tries to store the held state of `runId`. \return true when stored (or none was held).
    bool storeHeldState(std::int64_t runId);

    ScannerDeps d_;
    mutable std::mutex mutex_;
    std::condition_variable cv_;
    bool wake_ = false;
    std::atomic<bool> shutdown_{false};
    std::optional<std::int64_t> active_;
    std::set<std::int64_t> pauseRequested_;
    std::set<std::int64_t> cancelRequested_;
    std::set<std::int64_t> alarmResetRequested_;
    struct HeldState {
        RunState state = RunState::Paused;
        std::string reason;
    };
    std::map<std::int64_t, HeldState> held_; ///< run states not yet journaled (disk full)
    std::string activity_ = "starting";
    bool idle_ = false;
    std::thread thread_;
};

} // namespace slicestation::daemon
