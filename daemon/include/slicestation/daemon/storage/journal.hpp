#pragma once
/// The station's journal: one SQLite file (WAL, foreign keys, synchronous=FULL) holding every
/// run, slide, section, capture, registration and alert. Every state change is one transaction,
/// so a crash at any instant leaves either the old or the new state, never a mix.
///
/// Files are referenced only after they are complete on disk: callers write the image (atomic
/// rename + fsync) first and journal it second.
///
/// Schema versions live in `PRAGMA user_version`; open() applies the migrations a file lacks, all
/// in one transaction, and refuses a file written by a newer version (Unsupported). Version 2
/// (issue 18) adds the damage score, verdict and flag score of every registration (NULL, unknown,
/// for older rows) and the station settings kept in the journal. Version 3 (issue 19) adds each
/// registration's atlas plane: the planned one, the section's own match and the series model's
/// (NULL for older rows and for registrations made without matching).
///
/// Threading: every method is thread-safe (one connection behind a mutex); calls are short.
/// Errors: IoError (SQLite failure, message carries SQLite's text and the file), NotFound (no such
/// run/section/alert), InvalidArgument (a request that makes no sense in the record's state,
/// message says why), Unsupported (schema from the future).
#include "slicestation/core/result.hpp"
#include "slicestation/core/stage.hpp"
#include "slicestation/daemon/storage/alert_kind.hpp"

#include <nlohmann/json.hpp>

#include <cstdint>
#include <filesystem>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

struct sqlite3;

namespace slicestation::daemon {

enum class RunState { Queued, Running, Paused, Finished, Failed, Cancelled };
/// pending: not captured yet; captured: image stored, registration pending; registered: done;
/// damaged: registered and flagged, waiting for re-mount; rescan: re-mounted, to capture again;
/// failed: could not be captured or registered (reason says why).
enum class SectionState { Pending, Captured, Registered, Damaged, Rescan, Failed };

const char* toString(RunState s) noexcept;
const char* toString(SectionState s) noexcept;
std::optional<RunState> runStateFromString(std::string_view s) noexcept;
std::optional<SectionState> sectionStateFromString(std::string_view s) noexcept;
bool isTerminal(RunState s) noexcept; ///< finished, failed, cancelled

/// One section of a plan, as it is journalled when the run is submitted.
struct PlannedSection {
    int slideIndex = 0;
    std::string slideName;
    int index = 0; ///< within the slide
    std::string name;
    double xUm = 0, yUm = 0;          ///< centre, stage frame
    double widthUm = 0, heightUm = 0; ///< 0 = one field of view
    std::optional<int> expectedSlice; ///< atlas stack index
};

struct RunRecord {
    std::int64_t id = 0;
    std::string name;
    RunState state = RunState::Queued;
    std::string reason; ///< why it is paused/failed/cancelled
    nlohmann::json plan;
    nlohmann::json settings; ///< station settings snapshotted at submission
    std::string createdUtc, startedUtc, endedUtc;
    int sectionCount = 0;
    int doneCount = 0; ///< registered, damaged or failed
};

struct SectionRecord {
    std::int64_t id = 0;
    std::int64_t runId = 0;
    int slideIndex = 0;
    std::string slideName;
    int index = 0;
    std::string name;
    double xUm = 0, yUm = 0, widthUm = 0, heightUm = 0;
    std::optional<int> expectedSlice;
    SectionState state = SectionState::Pending;
    std::string reason;
    int attempts = 0; ///< captures stored so far
    /// Of the latest registration: its damage score in [0, 1] and verdict ("clean", "damaged",
    /// "check_registration"); empty/"" before the first registration and for registrations
    /// journalled before schema version 2 (unknown).
    std::optional<double> damageScore;
    std::string damageVerdict;
};

struct CaptureRecord {
    std::int64_t id = 0;
    std::int64_t sectionId = 0;
    int attempt = 0;       ///< 1 for the first capture, 2 after a rescan, ...
    std::string imagePath; ///< relative to the state directory
    double umPerPx = 0;
    hw::StagePosition stage;
    std::optional<double> focusScore;
    bool focusFound = false;
    int tiles = 1;
    std::int64_t exposureUs = 0;
    double gain = 1;
    std::string capturedUtc;
};

/// The series model's word on one section (pipeline/series_model.hpp), as the journal keeps it.
struct SeriesPlacement {
    double positionUm = 0; ///< the series' answer: its own match, or the line's when placed
    int slot = 0;          ///< place in the cutting sequence
    /// pipeline::toString(SeriesAnomaly): "none", "off-line", "skipped-before", "swapped",
    /// "out-of-order", "duplicate" or "placed-on-line" (the only values the journal accepts).
    std::string anomaly = "none";
    int missingBefore = 0; ///< for "skipped-before"
    double tiltLrDeg = 0;  ///< the series' cutting angle from its sections' own estimates
    double tiltDvDeg = 0;
};

struct RegistrationRecord {
    std::int64_t id = 0;
    std::int64_t captureId = 0;
    int atlasSlice = 0;
    std::optional<int> matchedSlice;
    bool damaged = false;
    double damageFraction = 0;
    std::string summary; ///< damage summary
    std::string warning; ///< e.g. the section matches another atlas slice
    double quality = 0;  ///< mask overlap of the registered atlas with the tissue, 0..1
    std::string resultPath, overlayPath, labelsPath; ///< relative to the state directory
    nlohmann::json result;
    std::string registeredUtc;
    /// Schema version 2. The section's damage score in [0, 1]; the station's verdict ("clean",
    /// "damaged" or "check_registration", the only values the journal accepts); the flag score
    /// the station applied. Unknown (nullopt / "") for rows journalled before version 2.
    std::optional<double> damageScore;
    std::string damageVerdict;
    std::optional<double> flagScore;
    /// Schema version 3 (issue 19): the planes. `atlasSlice` is the slice registered to (the
    /// found plane: the series' position rounded to the nearest stack slice). The planned slice
    /// and its position (the plan's, when it gives one); the section's own match (`matchedSlice`
    /// and its refined position); the series model's word, updated once the next section has
    /// confirmed it (Journal::updateSeries). All unknown for rows journalled before version 3.
    std::optional<int> plannedSlice;
    std::optional<double> plannedPositionUm;
    std::optional<double> matchedPositionUm;
    std::optional<double> foundPositionUm; ///< position of the slice registered to
    std::optional<SeriesPlacement> series;
    /// Schema version 4: the tilt of the plane registered to (degrees, as `atlas slice
    /// --tilt-*-deg`): 0 for the stack's straight slices, the run's found tilt once applied.
    /// Unknown for rows journalled before version 4.
    std::optional<double> foundTiltLrDeg;
    std::optional<double> foundTiltDvDeg;
};

/// A damage alert (kind damaged or check_registration) on a section and how it was answered,
/// with the score of the registration it was raised for: the latest registration of the section
/// journalled no later than the alert.
struct DamageFlag {
    std::int64_t alertId = 0;
    std::int64_t sectionId = 0;
    std::optional<std::int64_t> runId;
    std::string sectionName, slideName;
    AlertKind kind = AlertKind::Damaged;
    std::string raisedUtc;
    std::optional<std::string> acknowledgedUtc;
    std::string ackAction;
    std::optional<double> damageScore; ///< unknown for registrations before schema version 2
    std::optional<double> flagScore;   ///< the threshold the station applied then
};

struct AlertRecord {
    std::int64_t id = 0;
    std::optional<std::int64_t> runId;
    std::optional<std::int64_t> sectionId;
    AlertKind kind = AlertKind::Damaged; ///< stored and served as toString(kind)
    AlertSeverity severity = AlertSeverity::Info;
    std::string message;
    std::string raisedUtc;
    std::optional<std::string> acknowledgedUtc;
    std::string ackAction; ///< "rescan", "accept" or free text
};

class Journal {
public:
    /// Opens (creating when absent) the journal at `file` and migrates it.
    [[nodiscard]] static core::Result<std::unique_ptr<Journal>>
    open(const std::filesystem::path& file);
    ~Journal();
    Journal(const Journal&) = delete;
    Journal& operator=(const Journal&) = delete;

    static constexpr int kSchemaVersion = 4;

    // Runs ----------------------------------------------------------------------------------
    /// Journals a new queued run with its sections in one transaction.
    [[nodiscard]] core::Result<std::int64_t> createRun(const std::string& name,
                                                       const nlohmann::json& plan,
                                                       const nlohmann::json& settings,
                                                       const std::vector<PlannedSection>& sections);
    [[nodiscard]] core::Result<RunRecord> run(std::int64_t runId);
    [[nodiscard]] core::Result<std::vector<RunRecord>> runs();
    /// Sets the state (and reason); stamps started/ended times. Refuses to leave a terminal
    /// state (InvalidArgument) unless `reopen` (a rescan of a finished run).
    [[nodiscard]] core::Result<void> setRunState(std::int64_t runId, RunState state,
                                                 const std::string& reason = {},
                                                 bool reopen = false);
    /// The run to work on: a running one (resume after a crash) first, else the oldest queued.
    /// Paused runs wait for resume. Empty when there is nothing to do.
    [[nodiscard]] core::Result<std::optional<RunRecord>> nextRun();

    // Sections ------------------------------------------------------------------------------
    [[nodiscard]] core::Result<std::vector<SectionRecord>> sections(std::int64_t runId);
    [[nodiscard]] core::Result<SectionRecord> section(std::int64_t sectionId);
    /// The next section of `runId` to capture (pending or rescan), in plan order.
    [[nodiscard]] core::Result<std::optional<SectionRecord>>
    nextSectionToCapture(std::int64_t runId);
    /// Stores a complete capture and moves the section to `captured`, in one transaction.
    /// The attempt number is assigned here. \return the capture id.
    [[nodiscard]] core::Result<std::int64_t> recordCapture(CaptureRecord capture);
    [[nodiscard]] core::Result<std::vector<CaptureRecord>> captures(std::int64_t sectionId);
    [[nodiscard]] core::Result<CaptureRecord> capture(std::int64_t captureId);
    /// The capture whose image is `imagePath` (relative to the state directory), if any.
    [[nodiscard]] core::Result<std::optional<std::int64_t>>
    captureWithImage(const std::string& imagePath);
    /// Captures whose section is `captured` and that have no registration (after a crash).
    [[nodiscard]] core::Result<std::vector<std::int64_t>> capturesAwaitingRegistration();
    /// Stores the registration and moves the section to registered or damaged.
    [[nodiscard]] core::Result<std::int64_t> recordRegistration(RegistrationRecord registration);
    [[nodiscard]] core::Result<std::vector<RegistrationRecord>>
    registrations(std::int64_t sectionId);
    /// Marks a section failed with a reason (capture or registration gave up).
    /// Replaces the series model's word on a journalled registration (the model refits as later
    /// sections arrive; the slice registered to stays). NotFound, InvalidArgument (an anomaly
    /// the journal does not know).
    [[nodiscard]] core::Result<void> updateSeries(std::int64_t registrationId,
                                                  const SeriesPlacement& series);
    [[nodiscard]] core::Result<void> failSection(std::int64_t sectionId, const std::string& reason);
    /// After re-mounting: the section is captured again (its old records stay). A finished run
    /// is reopened (queued). InvalidArgument when the section is still pending or captured.
    [[nodiscard]] core::Result<void> requestRescan(std::int64_t sectionId);

    // Alerts --------------------------------------------------------------------------------
    [[nodiscard]] core::Result<std::int64_t> raiseAlert(AlertRecord alert);
    [[nodiscard]] core::Result<std::vector<AlertRecord>> alerts(bool openOnly);
    [[nodiscard]] core::Result<AlertRecord> alert(std::int64_t alertId);
    /// InvalidArgument when already acknowledged.
    [[nodiscard]] core::Result<AlertRecord> acknowledgeAlert(std::int64_t alertId,
                                                             const std::string& action);

    // Damage flags and station settings (journal_damage.cpp) --------------------------------
    /// Every alert of kind damaged or check_registration on a section raised at or after
    /// `sinceUtc` (an ISO 8601 prefix compared as text; "" = all), oldest first.
    [[nodiscard]] core::Result<std::vector<DamageFlag>> damageFlags(const std::string& sinceUtc);
    /// A station setting stored in the journal (e.g. "damage.flag_score"), with the UTC time it
    /// was set; nullopt when it was never set or has been cleared.
    struct Setting {
        nlohmann::json value;
        std::string setUtc;
    };
    [[nodiscard]] core::Result<std::optional<Setting>> setting(const std::string& key);
    [[nodiscard]] core::Result<void> setSetting(const std::string& key,
                                                const nlohmann::json& value);
    [[nodiscard]] core::Result<void> clearSetting(const std::string& key);

    /// `PRAGMA integrity_check` and `foreign_key_check`; IoError naming the first problem.
    [[nodiscard]] core::Result<void> checkIntegrity();

    /// Current UTC time, ISO 8601 with milliseconds (what every *Utc field holds).
    static std::string nowUtc();

private:
    Journal(sqlite3* db, std::filesystem::path file) : db_(db), file_(std::move(file)) {}
    core::Result<void> migrate();
    /// The series columns of registration `id`; the caller holds the mutex (and a transaction).
    core::Result<void> writeSeries(std::int64_t id, const SeriesPlacement& series);
    sqlite3* db_;
    std::filesystem::path file_;
    std::mutex mutex_;
};

nlohmann::json toJson(const RunRecord& r);
nlohmann::json toJson(const SectionRecord& s);
nlohmann::json toJson(const CaptureRecord& c);
nlohmann::json toJson(const RegistrationRecord& r); ///< without the full result; with "plane"
/// The planes of a registration (docs/atlas.md, "The daemon: the series model in a run"):
/// {"planned": {"slice", "position_um"} | null, "matched": {"slice", "position_um"} | null,
///  "found": {"slice", "position_um", "tilted": false}, "series": {"position_um", "slot",
///  "anomaly", "missing_before", "tilt_lr_deg", "tilt_dv_deg"} | null}.
nlohmann::json planeJson(const RegistrationRecord& r);
nlohmann::json toJson(const AlertRecord& a);

} // namespace slicestation::daemon
