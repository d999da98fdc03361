#pragma once
/// Registers captured sections on its own thread, so the stage never waits for registration.
///
/// For each capture: with check_atlas_match (or no planned slice) the section goes through the
/// run's series model (SeriesTracker, issue 19) and is registered to the slice the model says
/// when that lies beyond the tolerance from the planned one (recorded as a warning) or nothing
/// is planned; within the tolerance, and without matching, to its planned slice. Writes result JSON
/// (with the planned, matched and found planes), overlay PNG and atlas labels in the image frame
/// (each file atomically), then journals the registration. Once the model has confirmed its word on
/// a section (the next section arrived, or the run's last one), the journal's series columns are
/// updated and a section off the plan or flagged skipped/swapped/out of order/duplicate raises one
/// "atlas_mismatch" alert. A damaged section raises a "damaged" alert (re-mount). A section that
/// cannot be registered is marked failed with the reason and alerted.
///
/// Crash safety: the queue is not persistent: after a restart the daemon re-enqueues
/// Journal::capturesAwaitingRegistration().
/// Threading: enqueue()/idle()/waitIdle() from any thread; stop() joins.
#include "slicestation/daemon/alerts/notifier.hpp"
#include "slicestation/daemon/config/daemon_settings.hpp"
#include "slicestation/daemon/station/phase_stats.hpp"
#include "slicestation/daemon/station/registration_service.hpp"
#include "slicestation/daemon/station/series_tracker.hpp"
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
    /// The atlas_mismatch alert on a section whose series word is settled: when the series flags
    /// it (skipped-before, swapped, out-of-order, duplicate) or places it beyond
    /// `toleranceSlices` from `settled.expectedSlice` (the planned slice moved by the skips the
    /// model found so far; `plannedSlice` when unset); "" when neither.
    static std::string seriesAlertText(const std::string& label,
                                       const SeriesTracker::Settled& settled,
                                       std::optional<int> plannedSlice, int toleranceSlices);

private:
    void loop();
    void process(std::int64_t captureId);
    /// The slice to register to: the series model's (when matching runs and succeeds), else the
    /// planned one. A found slice beyond the tolerance from the planned one gives a warning.
    /// The error of matching when no slice is planned and matching fails.
    struct SliceChoice {
        std::optional<int> slice;                          ///< set on success
        std::optional<SeriesTracker::Placement> placement; ///< when matching ran and succeeded
        std::string warning;
        /// The tilt of the plane registered to (useTiltedPlane); 0: the stack's straight slice.
        double tiltLrDeg = 0, tiltDvDeg = 0;
    };
    core::Result<SliceChoice> chooseSlice(const RunRecord& run, const SectionRecord& section,
                                          const CaptureRecord& capture,
                                          const ScanSettings& settings);
    /// When the placement carries the run's tilt: the plane through `choice.slice`'s position
    /// cut at that tilt, written beside the capture (`base`.plane.tif, and
    /// `base`.plane-template.tif when the stack has template planes, `base`.plane-ids.tif with
    /// every atlas id when its slices keep them), is what `rq` registers to
    /// (its frame the tilted plane's). A plane that cannot be cut or written leaves the straight
    /// slice and says why in the choice's warning.
    void useTiltedPlane(SliceChoice& choice, const std::filesystem::path& base,
                        RegisterRequest& rq) const;
    /// The planes of the registration: found (`choice.slice`), planned, own match, series word.
    void setPlanes(RegistrationRecord& rec, const SectionRecord& section,
                   const SliceChoice& choice) const;
    /// Journals the series' confirmed word on each section and raises its alert (once).
    void settleSeries(const RunRecord& run, bool runComplete, int toleranceSlices);
    static std::string sectionLabel(const SectionRecord& section, std::int64_t runId);
    /// Journals the registration and tells: an event, and alerts for a mismatch or damage.
    void record(RegistrationRecord& rec, const RunRecord& run, const SectionRecord& section,
                const std::string& label);
    /// Computes the stack's matching features once.
    core::Result<void> loadFeatures();

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
    SeriesTracker series_;                          ///< worker thread only; uses features_
};

} // namespace slicestation::daemon
