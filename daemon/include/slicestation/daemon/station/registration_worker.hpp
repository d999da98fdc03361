#pragma once
/// Registers captured sections on its own thread, so the stage never waits for registration.
///
/// For each capture: (optionally) checks which atlas slice the section really matches and
/// records a warning beyond the tolerance, registers it to its expected slice (the plan is the
/// authority), writes result JSON, overlay PNG and atlas labels in the image frame (each file
/// atomically), then journals the registration. A damaged section raises a "damaged" alert
/// (re-mount). A section that cannot be registered is marked failed with the reason and alerted.
///
/// Crash safety: the queue is not persistent: after a restart the daemon re-enqueues
/// Journal::capturesAwaitingRegistration().
/// Threading: enqueue()/idle()/waitIdle() from any thread; stop() joins.
#include "slicestation/daemon/alerts/notifier.hpp"
#include "slicestation/daemon/config/daemon_settings.hpp"
#include "slicestation/daemon/station/phase_stats.hpp"
#include "slicestation/daemon/storage/atlas_stack.hpp"
#include "slicestation/daemon/storage/journal.hpp"
#include "slicestation/pipeline/atlas_matching.hpp"
#include "slicestation/pipeline/registration.hpp"

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <filesystem>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

namespace slicestation::daemon {

class RegistrationWorker {
public:
    RegistrationWorker(Journal& journal, Notifier& notifier, const AtlasStack& stack,
                       std::filesystem::path stateDir, PhaseStats& stats);
    ~RegistrationWorker();
    RegistrationWorker(const RegistrationWorker&) = delete;
    RegistrationWorker& operator=(const RegistrationWorker&) = delete;

    void start();
    void enqueue(std::int64_t captureId);
    /// Nothing queued and nothing in progress.
    bool idle() const;
    /// Blocks until idle or `timeout`; \return idle.
    bool waitIdle(std::chrono::milliseconds timeout) const;
    /// Finishes the registration in progress, drops the queue (the journal keeps it), joins.
    void stop() noexcept;

    /// The station's verdict on a registration (docs/damage.md, "The score, the threshold and
    /// the lab's report"): the pipeline's "check_registration" stays; otherwise "damaged" when
    /// the score reaches `flagScore` (the run's snapshot), else "clean". Sets damageScore,
    /// flagScore, damageVerdict and damaged.
    static void applyFlagScore(RegistrationRecord& rec, const pipeline::Registration& reg,
                               double flagScore);
    /// The message of the damaged or check_registration alert, with the score (2 decimals).
    static std::string damageAlertText(const RegistrationRecord& rec, const std::string& label);

private:
    void loop();
    void process(std::int64_t captureId);
    /// The slice to register to: the planned one; the matched one when none is planned. With
    /// settings.checkAtlasMatch the whole stack is searched and a match beyond the tolerance
    /// gives a warning. InvalidArgument-like errors when no slice is planned and matching fails.
    struct SliceChoice {
        std::optional<int> slice;   ///< set on success
        std::optional<int> matched; ///< what matching found, when it ran and succeeded
        std::string warning;
    };
    core::Result<SliceChoice> chooseSlice(const SectionRecord& section,
                                          const CaptureRecord& capture,
                                          const ScanSettings& settings);
    /// Journals the registration and tells: an event, and alerts for a mismatch or damage.
    void record(RegistrationRecord& rec, const RunRecord& run, const SectionRecord& section,
                const std::string& label);
    /// The stack slice the image matches best (within `window` of `expected` when given).
    core::Result<int> matchToStack(const std::filesystem::path& image, double umPerPx,
                                   std::optional<int> expected, int window);

    Journal& journal_;
    Notifier& notifier_;
    const AtlasStack& stack_;
    std::filesystem::path stateDir_;
    PhaseStats& stats_;
    mutable std::mutex mutex_;
    mutable std::condition_variable cv_;
    std::deque<std::int64_t> queue_;
    bool busy_ = false;
    bool stopping_ = false;
    std::thread thread_;
    std::vector<pipeline::SliceFeatures> features_; ///< worker thread only
};

} // namespace slicestation::daemon
