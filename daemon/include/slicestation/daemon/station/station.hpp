#pragma once
/// The station assembled: journal, atlas stack, devices, registration worker, scan loop and
/// notifier, around one state directory:
/// ```
/// STATE_DIR/journal.sqlite        the journal (journal.hpp)
/// STATE_DIR/atlas-builtin/        the built-in atlas stack, written on first start
/// STATE_DIR/runs/<run>/<slide>/   <section>-a<attempt>.ome.tif and its registration outputs
/// ```
/// Threading: create() and the accessors from the main thread; submitPlan() and the control
/// calls from any thread (the HTTP server's).
#include "slicestation/core/camera.hpp"
#include "slicestation/core/stage.hpp"
#include "slicestation/daemon/alerts/notifier.hpp"
#include "slicestation/daemon/config/daemon_settings.hpp"
#include "slicestation/daemon/station/phase_stats.hpp"
#include "slicestation/daemon/station/registration_worker.hpp"
#include "slicestation/daemon/station/scanner.hpp"
#include "slicestation/daemon/station/station_api.hpp"
#include "slicestation/daemon/storage/atlas_stack.hpp"
#include "slicestation/daemon/storage/journal.hpp"

#include <nlohmann/json.hpp>

#include <filesystem>
#include <functional>
#include <memory>
#include <mutex>

namespace slicestation::daemon {

class ProgressWatchdog;

struct StationParts {
    std::unique_ptr<hw::Stage> stage;
    std::unique_ptr<hw::Camera> camera;
    bool simulatedStage = false;
    bool simulatedCamera = false;
    DaemonSettings settings;
    std::filesystem::path stateDir;
    /// Default: availableBytes. Tests inject a full disk.
    std::function<core::Result<std::uint64_t>(const std::filesystem::path&)> freeSpace;
    ProgressWatchdog* watchdog = nullptr;
    std::function<void(const std::string&)> status;
    /// Told every position the stage settles at, autofocus steps included (a simulated camera
    /// renders what lies there). The stage is wrapped to report it.
    std::function<void(const hw::StagePosition&)> stageMoved;
    /// Outward alert channels, registered before anything can be raised (a "restarted" alert
    /// is raised while the station is created).
    std::vector<Notifier::AlertChannel> alertChannels;
};

class Station final : public StationApi {
public:
    /// Opens the journal, prepares the atlas stack, removes half-written temporary files, and
    /// raises a "restarted" alert when a run was in progress (a crash or watchdog restart).
    [[nodiscard]] static core::Result<std::unique_ptr<Station>> create(StationParts parts);
    ~Station();

    /// Re-queues unregistered captures, starts the worker and the scan loop.
    void start();
    /// Clean stop: stage stopped, current transaction finished, threads joined.
    void stop() noexcept;

    // StationApi (station_api.hpp): what the HTTP API asks; the views are in station_views.cpp.
    nlohmann::json status() override;
    [[nodiscard]] core::Result<std::vector<RunRecord>> runs() override;
    [[nodiscard]] core::Result<RunRecord> run(std::int64_t runId) override;
    [[nodiscard]] core::Result<std::vector<SectionRecord>> sections(std::int64_t runId) override;
    /// Export rows of a run: per section the image path, stage position, atlas slice,
    /// registration quality and damage. Format "json" or "csv".
    [[nodiscard]] core::Result<std::string> exportRun(std::int64_t runId,
                                                      const std::string& format) override;
    /// Section detail: record, captures, registrations (with region names), alerts.
    [[nodiscard]] core::Result<nlohmann::json> sectionDetail(std::int64_t sectionId) override;
    [[nodiscard]] core::Result<std::vector<AlertRecord>> alerts(bool openOnly) override;
    /// The latest frame the camera delivered (autofocus frames included), for the live view;
    /// null before the first. Any thread.
    std::shared_ptr<const hw::Frame> liveFrame() const override;
    [[nodiscard]] core::Result<cv::Mat> sectionImage(std::int64_t sectionId, bool overlay) override;
    [[nodiscard]] core::Result<std::string> sectionCounts(std::int64_t sectionId) override;
    [[nodiscard]] core::Result<std::string> runCounts(std::int64_t runId) override;
    [[nodiscard]] core::Result<ImagePyramid> sectionPyramid(std::int64_t sectionId) override;
    [[nodiscard]] core::Result<cv::Mat> sectionTile(std::int64_t sectionId, int level, int x,
                                                    int y) override;
    [[nodiscard]] core::Result<RegionAtPixel> regionAt(std::int64_t sectionId, int x, int y,
                                                       int ofWidth) override;
    /// Validates and journals a plan (TOML/JSON already parsed) with a snapshot of the scan
    /// settings. \return the run id; InvalidArgument naming the field.
    [[nodiscard]] core::Result<std::int64_t> submitPlan(const nlohmann::json& plan,
                                                        const std::string& origin) override;
    [[nodiscard]] core::Result<void> pauseRun(std::int64_t runId) override {
        return scanner_->pause(runId);
    }
    [[nodiscard]] core::Result<void> resumeRun(std::int64_t runId, bool resetStageAlarm) override {
        return scanner_->resume(runId, resetStageAlarm);
    }
    [[nodiscard]] core::Result<void> cancelRun(std::int64_t runId) override {
        return scanner_->cancel(runId);
    }
    [[nodiscard]] core::Result<void> requestRescan(std::int64_t sectionId) override;
    [[nodiscard]] core::Result<AlertRecord> acknowledgeAlert(std::int64_t alertId,
                                                             const std::string& action) override;
    [[nodiscard]] core::Result<nlohmann::json> damageReport(const std::string& sinceUtc,
                                                            double targetFalseAlarmRate) override;
    [[nodiscard]] core::Result<nlohmann::json> damageThreshold() override;
    [[nodiscard]] core::Result<nlohmann::json>
    setDamageThreshold(std::optional<double> flagScore) override;
    /// The [scan] settings a run submitted now snapshots: the station file's, with the flag
    /// score set through the API (journal setting "damage.flag_score") when there is one.
    [[nodiscard]] core::Result<ScanSettings> settingsForNewRun();
    void addListener(std::function<void(const StationEvent&)> listener) override {
        notifier_->addListener(std::move(listener));
    }

    Journal& journal() { return *journal_; }
    Scanner& scanner() { return *scanner_; }
    Notifier& notifier() { return *notifier_; }
    PhaseStats& stats() { return stats_; }
    const AtlasStack& atlas() const { return stack_; }
    const std::filesystem::path& stateDir() const { return parts_.stateDir; }
    const DaemonSettings& settings() const { return parts_.settings; }
    /// No run left to work on and nothing being registered.
    bool idle() const { return scanner_->idle(); }

private:
    explicit Station(StationParts parts) : parts_(std::move(parts)) {}
    StationParts parts_;
    std::unique_ptr<Journal> journal_;
    std::unique_ptr<Notifier> notifier_;
    AtlasStack stack_;
    std::vector<double> slicePositionsUm_;
    PhaseStats stats_;
    std::unique_ptr<RegistrationWorker> worker_;
    std::unique_ptr<Scanner> scanner_;
    mutable std::mutex liveMutex_;
    std::shared_ptr<const hw::Frame> live_;
    /// A stage position seen: `at` (stage clock) for a read during a move, nullopt for the
    /// settled position after one. Kept for status(); published as "stage_position".
    void noteStagePosition(const hw::StagePosition& p,
                           std::optional<std::chrono::steady_clock::time_point> at);
    std::mutex stageMutex_;
    std::optional<hw::StagePosition> stage_;
    bool stageMoving_ = false;
    bool stageAnnounced_ = false; ///< a move's position was published: publish where it ended
    std::optional<std::chrono::steady_clock::time_point> lastStageEvent_;
    std::mutex labelsMutex_; ///< the labels regionAt() read last, kept for the next pixel
    std::string labelsPath_;
    cv::Mat labels_;
};

/// The stack named by settings.atlas: "builtin" (written under stateDir on first use) or a
/// stack directory.
[[nodiscard]] core::Result<AtlasStack> openAtlasStack(const DaemonSettings& settings,
                                                      const std::filesystem::path& stateDir);

} // namespace slicestation::daemon
