#pragma once
/// What the outward parts (the HTTP API) may ask of the station, and nothing more: the journal's
/// records, the station's views of them, the stored images, and the control requests. Station
/// is the model; tests use a fake (tests/daemon/http/fake_station.hpp).
///
/// Errors follow one rule, so that the HTTP API maps them with one table (http/http_util.hpp):
///   reads:    NotFound (no such record, or nothing of it yet), InvalidArgument / OutOfRange /
///             Unsupported (the request's values), anything else a fault of the station;
///   controls: NotFound (no such record), InvalidArgument (the record is not in a state for
///             the request, e.g. resuming a run that is not paused), OutOfRange / Unsupported
///             (a bad value), anything else a fault of the station.
/// Threading: every call from any thread (the HTTP server's workers).
#include "slicestation/core/frame.hpp"
#include "slicestation/core/result.hpp"
#include "slicestation/daemon/alerts/notifier.hpp"
#include "slicestation/daemon/storage/journal.hpp"

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

namespace slicestation::daemon {

/// The atlas region at a pixel of a section's latest registered capture.
struct RegionAtPixel {
    std::int32_t id = 0;       ///< 0: outside the brain
    int x = 0, y = 0;          ///< the full-resolution pixel looked at
    std::string name, acronym; ///< empty when the ontology lacks the id (or id 0)
};

/// The tile pyramid of a section's stored image (OME-TIFF sub-resolutions, docs/images.md).
struct ImagePyramid {
    int tileSizePx = 0;
    std::vector<cv::Size> levels; ///< level 0: full resolution; each next one half the size
};

class StationApi {
public:
    virtual ~StationApi() = default;

    // Reads.
    /// {"state", "activity", "active_run", "simulated", "open_alerts", "phases", ...}
    virtual nlohmann::json status() = 0;
    [[nodiscard]] virtual core::Result<std::vector<RunRecord>> runs() = 0;
    [[nodiscard]] virtual core::Result<RunRecord> run(std::int64_t runId) = 0;
    /// NotFound when the run does not exist.
    [[nodiscard]] virtual core::Result<std::vector<SectionRecord>> sections(std::int64_t runId) = 0;
    /// Format "json", "csv", "quicknii" or "qupath" (export/run_export.hpp; else
    /// InvalidArgument).
    [[nodiscard]] virtual core::Result<std::string> exportRun(std::int64_t runId,
                                                              const std::string& format) = 0;
    [[nodiscard]] virtual core::Result<nlohmann::json> sectionDetail(std::int64_t sectionId) = 0;
    /// The stored alerts (all, or the open ones), then those held in memory while the disk is
    /// full (negative ids, open; stored and renumbered once the journal takes writes again).
    [[nodiscard]] virtual core::Result<std::vector<AlertRecord>> alerts(bool openOnly) = 0;
    /// The latest camera frame, null before the first.
    virtual std::shared_ptr<const hw::Frame> liveFrame() const = 0;
    /// The image of a section's latest capture, or (`overlay`) its registration overlay, as
    /// stored. NotFound: no such section, no capture yet, not registered yet (overlay); IoError:
    /// the stored file is unreadable or its journal path leaves the state directory.
    [[nodiscard]] virtual core::Result<cv::Mat> sectionImage(std::int64_t sectionId,
                                                             bool overlay) = 0;
    /// The atlas region at pixel (x, y) of the section's latest registered capture; with
    /// ofWidth > 0, (x, y) is a pixel of that image scaled to width ofWidth. NotFound as
    /// sectionImage(overlay); InvalidArgument: the pixel lies outside the image; IoError: the
    /// stored labels are unreadable.
    [[nodiscard]] virtual core::Result<RegionAtPixel> regionAt(std::int64_t sectionId, int x, int y,
                                                               int ofWidth) = 0;
    /// Cells per region (docs/cells.md): the COUNTS.csv of the section's latest registered
    /// capture, or (`runId` form) the run's summed run-counts.csv. NotFound: no such section or
    /// run, not registered yet, or counting was not asked for (scan.count_cells); IoError: the
    /// file is unreadable. Not pure: a station without counting keeps the NotFound default.
    [[nodiscard]] virtual core::Result<std::string> sectionCounts(std::int64_t sectionId) {
        return core::makeError(core::ErrorCode::NotFound,
                               "section " + std::to_string(sectionId) + " has no cell counts");
    }
    [[nodiscard]] virtual core::Result<std::string> runCounts(std::int64_t runId) {
        return core::makeError(core::ErrorCode::NotFound,
                               "run " + std::to_string(runId) + " has no cell counts");
    }

    /// The pyramid of the section's latest image. NotFound as sectionImage; Unsupported: the
    /// stored image is not tiled (written before pyramids); IoError: unreadable.
    [[nodiscard]] virtual core::Result<ImagePyramid> sectionPyramid(std::int64_t /*sectionId*/) {
        return core::makeError(core::ErrorCode::Unsupported, "no image pyramids here");
    }
    /// Tile (x, y) of `level` of the section's latest image, 8-bit for display (grey or BGR;
    /// deeper images stretched by the percentiles of the smallest level, the same for every
    /// tile). NotFound as sectionImage, or no such level or tile; Unsupported: not tiled.
    [[nodiscard]] virtual core::Result<cv::Mat> sectionTile(std::int64_t /*sectionId*/,
                                                            int /*level*/, int /*x*/, int /*y*/) {
        return core::makeError(core::ErrorCode::Unsupported, "no image pyramids here");
    }

    // Controls.
    /// Validates and journals a plan (TOML/JSON already parsed). \return the run id.
    [[nodiscard]] virtual core::Result<std::int64_t> submitPlan(const nlohmann::json& plan,
                                                                const std::string& origin) = 0;
    [[nodiscard]] virtual core::Result<void> pauseRun(std::int64_t runId) = 0;
    [[nodiscard]] virtual core::Result<void> resumeRun(std::int64_t runId,
                                                       bool resetStageAlarm) = 0;
    [[nodiscard]] virtual core::Result<void> cancelRun(std::int64_t runId) = 0;
    [[nodiscard]] virtual core::Result<void> requestRescan(std::int64_t sectionId) = 0;
    /// Acknowledges an alert with `action` ("rescan": the alert's section is rescanned first,
    /// InvalidArgument when it concerns no section, or when it is held in memory (a negative
    /// id); "accept" or any text).
    [[nodiscard]] virtual core::Result<AlertRecord> acknowledgeAlert(std::int64_t alertId,
                                                                     const std::string& action) = 0;

    // The lab's damage report and threshold (docs/damage.md). A station that keeps no journal
    // (a test double) answers Unsupported.
    /// The report over the damage flags raised at or after `sinceUtc` (parseSinceUtc; "" = all)
    /// for a target false-alarm rate in [0, 1], with the flag score in force now.
    /// InvalidArgument for a bad date or rate.
    [[nodiscard]] virtual core::Result<nlohmann::json> damageReport(const std::string& sinceUtc,
                                                                    double targetFalseAlarmRate) {
        (void)sinceUtc;
        (void)targetFalseAlarmRate;
        return core::makeError(core::ErrorCode::Unsupported, "this station keeps no damage report");
    }
    /// {"flag_score", "source": "station file" | "set", "set_utc"}: the flag score the next run
    /// snapshots.
    [[nodiscard]] virtual core::Result<nlohmann::json> damageThreshold() {
        return core::makeError(core::ErrorCode::Unsupported,
                               "this station has no damage threshold");
    }
    /// Stores `flagScore` (in [0, 1], else OutOfRange) in the journal as the flag score of the
    /// runs submitted from now on; nullopt clears it (back to the station file's). \return as
    /// damageThreshold().
    [[nodiscard]] virtual core::Result<nlohmann::json>
    setDamageThreshold(std::optional<double> flagScore) {
        (void)flagScore;
        return core::makeError(core::ErrorCode::Unsupported,
                               "this station has no damage threshold");
    }

    /// Every station event from now on (called on the raiser's thread; must not block).
    virtual void addListener(std::function<void(const StationEvent&)> listener) = 0;
};

} // namespace slicestation::daemon
