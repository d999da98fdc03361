// The SQLite journal. Every public method takes the mutex, and every change runs inside one
// transaction (BEGIN IMMEDIATE .. COMMIT) so a kill at any point leaves a consistent file.
#include "slicestation/daemon/storage/journal.hpp"

#include "journal_sql.hpp"

#include <sqlite3.h>

#include <array>
#include <cerrno>
#include <chrono>
#include <cstdio>
#include <ctime>
#include <utility>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using core::Result;
using namespace journal_sql;

namespace {

constexpr std::array<const char*, 6> kRunStates = {"queued",   "running", "paused",
                                                   "finished", "failed",  "cancelled"};
constexpr std::array<const char*, 6> kSectionStates = {"pending", "captured", "registered",
                                                       "damaged", "rescan",   "failed"};

// Version 1 of the schema. Later versions append migrations; never edit a shipped one.
constexpr const char* kMigration1 = R"sql(
CREATE TABLE runs (
    id INTEGER PRIMARY KEY,
    name TEXT NOT NULL,
    state TEXT NOT NULL CHECK (state IN ('queued','running','paused','finished','failed','cancelled')),
    reason TEXT NOT NULL DEFAULT '',
    plan_json TEXT NOT NULL,
    settings_json TEXT NOT NULL,
    created_utc TEXT NOT NULL,
    started_utc TEXT NOT NULL DEFAULT '',
    ended_utc TEXT NOT NULL DEFAULT ''
);
CREATE TABLE sections (
    id INTEGER PRIMARY KEY,
    run_id INTEGER NOT NULL REFERENCES runs(id) ON DELETE CASCADE,
    slide_index INTEGER NOT NULL,
    slide_name TEXT NOT NULL,
    idx INTEGER NOT NULL,
    name TEXT NOT NULL,
    x_um REAL NOT NULL, y_um REAL NOT NULL,
    width_um REAL NOT NULL, height_um REAL NOT NULL,
    expected_slice INTEGER,
    state TEXT NOT NULL CHECK (state IN ('pending','captured','registered','damaged','rescan','failed')),
    reason TEXT NOT NULL DEFAULT '',
    UNIQUE (run_id, slide_index, idx)
);
CREATE TABLE captures (
    id INTEGER PRIMARY KEY,
    section_id INTEGER NOT NULL REFERENCES sections(id) ON DELETE CASCADE,
    attempt INTEGER NOT NULL,
    image_path TEXT NOT NULL,
    um_per_px REAL NOT NULL CHECK (um_per_px > 0),
    stage_x_um REAL NOT NULL, stage_y_um REAL NOT NULL, stage_z_um REAL NOT NULL,
    focus_score REAL,
    focus_found INTEGER NOT NULL,
    tiles INTEGER NOT NULL,
    exposure_us INTEGER NOT NULL,
    gain REAL NOT NULL,
    captured_utc TEXT NOT NULL,
    UNIQUE (section_id, attempt)
);
CREATE TABLE registrations (
    id INTEGER PRIMARY KEY,
    capture_id INTEGER NOT NULL UNIQUE REFERENCES captures(id) ON DELETE CASCADE,
    atlas_slice INTEGER NOT NULL,
    matched_slice INTEGER,
    damaged INTEGER NOT NULL,
    damage_fraction REAL NOT NULL,
    summary TEXT NOT NULL,
    warning TEXT NOT NULL,
    quality REAL NOT NULL,
    result_path TEXT NOT NULL,
    overlay_path TEXT NOT NULL,
    labels_path TEXT NOT NULL,
    result_json TEXT NOT NULL,
    registered_utc TEXT NOT NULL
);
CREATE TABLE alerts (
    id INTEGER PRIMARY KEY,
    run_id INTEGER REFERENCES runs(id) ON DELETE SET NULL,
    section_id INTEGER REFERENCES sections(id) ON DELETE SET NULL,
    kind TEXT NOT NULL,
    severity TEXT NOT NULL CHECK (severity IN ('info','warning','critical')),
    message TEXT NOT NULL,
    raised_utc TEXT NOT NULL,
    acknowledged_utc TEXT,
    ack_action TEXT NOT NULL DEFAULT ''
);
CREATE INDEX sections_by_run ON sections(run_id, slide_index, idx);
CREATE INDEX captures_by_section ON captures(section_id, attempt);
CREATE INDEX alerts_open ON alerts(acknowledged_utc);
)sql";

// Version 2: the damage score and verdict of every registration, the threshold the station
// applied to it, and the station's own settings (the lab's learned damage threshold). Rows from
// version 1 keep NULL there: their score and verdict are unknown (docs/damage.md).
constexpr const char* kMigration2 = R"sql(
ALTER TABLE registrations ADD COLUMN damage_score REAL
    CHECK (damage_score IS NULL OR (damage_score >= 0 AND damage_score <= 1));
ALTER TABLE registrations ADD COLUMN damage_verdict TEXT
    CHECK (damage_verdict IS NULL OR damage_verdict IN ('clean','damaged','check_registration'));
ALTER TABLE registrations ADD COLUMN flag_score REAL
    CHECK (flag_score IS NULL OR (flag_score >= 0 AND flag_score <= 1));
CREATE TABLE station_settings (
    key TEXT PRIMARY KEY,
    value_json TEXT NOT NULL,
    set_utc TEXT NOT NULL
);
CREATE INDEX alerts_by_kind ON alerts(kind, raised_utc);
)sql";

const std::array<const char*, 4> kMigrations = {kMigration1, kMigration2, kMigration3, kMigration4};
static_assert(std::tuple_size_v<decltype(kMigrations)> == Journal::kSchemaVersion);

} // namespace

const char* toString(RunState s) noexcept {
    return kRunStates[static_cast<std::size_t>(s)];
}
const char* toString(SectionState s) noexcept {
    return kSectionStates[static_cast<std::size_t>(s)];
}
std::optional<RunState> runStateFromString(std::string_view s) noexcept {
    for (std::size_t i = 0; i < kRunStates.size(); ++i)
        if (s == kRunStates[i])
            return static_cast<RunState>(i);
    return std::nullopt;
}
std::optional<SectionState> sectionStateFromString(std::string_view s) noexcept {
    for (std::size_t i = 0; i < kSectionStates.size(); ++i)
        if (s == kSectionStates[i])
            return static_cast<SectionState>(i);
    return std::nullopt;
}
bool isTerminal(RunState s) noexcept {
    return s == RunState::Finished || s == RunState::Failed || s == RunState::Cancelled;
}

std::string Journal::nowUtc() {
    const auto now = std::chrono::system_clock::now();
    const auto t = std::chrono::system_clock::to_time_t(now);
    const auto ms =
        std::chrono::duration_cast<std::chrono::milliseconds>(now.time_since_epoch()) % 1000;
    std::tm tm{};
    gmtime_r(&t, &tm);
    char buf[64];
    std::snprintf(buf, sizeof buf, "%04d-%02d-%02dT%02d:%02d:%02d.%03dZ", tm.tm_year + 1900,
                  tm.tm_mon + 1, tm.tm_mday, tm.tm_hour, tm.tm_min, tm.tm_sec,
                  static_cast<int>(ms.count()));
    return buf;
}

Result<std::unique_ptr<Journal>> Journal::open(const std::filesystem::path& file) {
    sqlite3* db = nullptr;
    const int rc = sqlite3_open_v2(
        file.c_str(), &db, SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE | SQLITE_OPEN_FULLMUTEX,
        nullptr);
    if (rc != SQLITE_OK) {
        std::string msg = db ? sqlite3_errmsg(db) : sqlite3_errstr(rc);
        sqlite3_close(db);
        return makeError(ErrorCode::IoError, "journal " + file.string() + ": cannot open: " + msg);
    }
    std::unique_ptr<Journal> j(new Journal(db, file));
    sqlite3_busy_timeout(db, 5000);
    // WAL keeps readers (the HTTP API) off the writer's back; FULL syncs every commit so a power
    // cut loses no committed transaction.
    const char* pragmas =
        "PRAGMA journal_mode=WAL; PRAGMA synchronous=FULL; PRAGMA foreign_keys=ON;";
    if (sqlite3_exec(db, pragmas, nullptr, nullptr, nullptr) != SQLITE_OK)
        return sqlError(db, file, "setting pragmas");
    {
        Statement st(db, "SELECT count(*) FROM sqlite_master");
        if (!st.ok() || st.step() != SQLITE_ROW)
            return sqlError(db, file, "not a journal (is it an SQLite database?)");
    }
    if (auto m = j->migrate(); !m)
        return m.error();
    return j;
}

Journal::~Journal() {
    sqlite3_close(db_);
}

Result<void> Journal::migrate() {
    std::lock_guard lock(mutex_);
    int version = 0;
    {
        Statement st(db_, "PRAGMA user_version");
        if (!st.ok() || st.step() != SQLITE_ROW)
            return sqlError(db_, file_, "reading user_version");
        version = st.i32(0);
    }
    if (version > kSchemaVersion)
        return makeError(ErrorCode::Unsupported,
                         "journal " + file_.string() + ": schema version " +
                             std::to_string(version) + " is newer than this slicestation (" +
                             std::to_string(kSchemaVersion) + "); refusing to touch it");
    if (version == kSchemaVersion)
        return {};
    // Every missing version in one transaction (one synced commit, which keeps a fresh station's
    // start short): a file is either migrated to the current version or left as it was.
    Transaction tx(db_);
    if (!tx.began())
        return sqlError(db_, file_, "begin migration");
    for (int v = version; v < kSchemaVersion; ++v)
        if (sqlite3_exec(db_, kMigrations[static_cast<std::size_t>(v)], nullptr, nullptr,
                         nullptr) != SQLITE_OK)
            return sqlError(db_, file_, ("migration to version " + std::to_string(v + 1)).c_str());
    const std::string setVersion = "PRAGMA user_version = " + std::to_string(kSchemaVersion);
    if (sqlite3_exec(db_, setVersion.c_str(), nullptr, nullptr, nullptr) != SQLITE_OK ||
        !tx.commit())
        return sqlError(db_, file_, "commit migration");
    return {};
}

Result<std::int64_t> Journal::createRun(const std::string& name, const nlohmann::json& plan,
                                        const nlohmann::json& settings,
                                        const std::vector<PlannedSection>& sections) {
    std::lock_guard lock(mutex_);
    Transaction tx(db_);
    if (!tx.began())
        return sqlError(db_, file_, "begin");
    Statement ins(db_, "INSERT INTO runs (name, state, plan_json, settings_json, created_utc) "
                       "VALUES (?, 'queued', ?, ?, ?)");
    ins.bind(1, name).bind(2, plan.dump()).bind(3, settings.dump()).bind(4, nowUtc());
    if (ins.step() != SQLITE_DONE)
        return sqlError(db_, file_, "insert run");
    const std::int64_t runId = sqlite3_last_insert_rowid(db_);
    for (const auto& s : sections) {
        Statement st(db_, "INSERT INTO sections (run_id, slide_index, slide_name, idx, name, x_um, "
                          "y_um, width_um, height_um, expected_slice, state) "
                          "VALUES (?,?,?,?,?,?,?,?,?,?,'pending')");
        st.bind(1, runId).bind(2, s.slideIndex).bind(3, s.slideName).bind(4, s.index);
        st.bind(5, s.name).bind(6, s.xUm).bind(7, s.yUm).bind(8, s.widthUm).bind(9, s.heightUm);
        st.bind(10, s.expectedSlice);
        if (st.step() != SQLITE_DONE)
            return sqlError(db_, file_, "insert section");
    }
    if (!tx.commit())
        return sqlError(db_, file_, "commit run");
    return runId;
}

Result<RunRecord> Journal::run(std::int64_t runId) {
    std::lock_guard lock(mutex_);
    Statement st(db_,
                 (std::string("SELECT ") + kRunColumns + " FROM runs r WHERE r.id = ?").c_str());
    st.bind(1, runId);
    return readOne<RunRecord>(st, db_, file_, "read run", "no run " + std::to_string(runId),
                              readRun);
}

Result<std::vector<RunRecord>> Journal::runs() {
    std::lock_guard lock(mutex_);
    Statement st(db_,
                 (std::string("SELECT ") + kRunColumns + " FROM runs r ORDER BY r.id").c_str());
    return readAll<RunRecord>(st, db_, file_, "list runs", readRun);
}

Result<void> Journal::setRunState(std::int64_t runId, RunState state, const std::string& reason,
                                  bool reopen) {
    std::lock_guard lock(mutex_);
    Transaction tx(db_);
    if (!tx.began())
        return sqlError(db_, file_, "begin");
    Statement cur(db_, "SELECT state FROM runs WHERE id = ?");
    cur.bind(1, runId);
    const int rc = cur.step();
    if (rc == SQLITE_DONE)
        return makeError(ErrorCode::NotFound, "no run " + std::to_string(runId));
    if (rc != SQLITE_ROW)
        return sqlError(db_, file_, "read run state");
    const auto from = runStateFromString(cur.text(0)).value_or(RunState::Failed);
    if (isTerminal(from) && !reopen && from != state)
        return makeError(ErrorCode::InvalidArgument, std::string("run ") + std::to_string(runId) +
                                                         " is " + toString(from) +
                                                         "; it cannot become " + toString(state));
    const std::string now = nowUtc();
    Statement up(
        db_,
        "UPDATE runs SET state = ?, reason = ?, "
        "started_utc = CASE WHEN ? = 'running' AND started_utc = '' THEN ? ELSE started_utc END, "
        "ended_utc = CASE WHEN ? IN ('finished','failed','cancelled') THEN ? ELSE '' END "
        "WHERE id = ?");
    up.bind(1, toString(state)).bind(2, reason).bind(3, toString(state)).bind(4, now);
    up.bind(5, toString(state)).bind(6, now).bind(7, runId);
    if (up.step() != SQLITE_DONE)
        return sqlError(db_, file_, "update run state");
    if (!tx.commit())
        return sqlError(db_, file_, "commit run state");
    return {};
}

Result<std::optional<RunRecord>> Journal::nextRun() {
    std::lock_guard lock(mutex_);
    Statement st(db_, (std::string("SELECT ") + kRunColumns +
                       " FROM runs r WHERE r.state IN ('running','queued') "
                       "ORDER BY r.state = 'running' DESC, r.id LIMIT 1")
                          .c_str());
    const int rc = st.step();
    if (rc == SQLITE_DONE)
        return std::optional<RunRecord>();
    if (rc != SQLITE_ROW)
        return sqlError(db_, file_, "next run");
    return std::optional<RunRecord>(readRun(st));
}

Result<std::vector<SectionRecord>> Journal::sections(std::int64_t runId) {
    std::lock_guard lock(mutex_);
    Statement st(db_, (std::string("SELECT ") + kSectionColumns +
                       " FROM sections s WHERE s.run_id = ? ORDER BY s.slide_index, s.idx")
                          .c_str());
    st.bind(1, runId);
    return readAll<SectionRecord>(st, db_, file_, "list sections", readSection);
}

Result<SectionRecord> Journal::section(std::int64_t sectionId) {
    std::lock_guard lock(mutex_);
    Statement st(
        db_,
        (std::string("SELECT ") + kSectionColumns + " FROM sections s WHERE s.id = ?").c_str());
    st.bind(1, sectionId);
    return readOne<SectionRecord>(st, db_, file_, "read section",
                                  "no section " + std::to_string(sectionId), readSection);
}

Result<std::optional<SectionRecord>> Journal::nextSectionToCapture(std::int64_t runId) {
    std::lock_guard lock(mutex_);
    Statement st(db_, (std::string("SELECT ") + kSectionColumns +
                       " FROM sections s WHERE s.run_id = ? AND s.state IN ('pending','rescan') "
                       "ORDER BY s.slide_index, s.idx LIMIT 1")
                          .c_str());
    st.bind(1, runId);
    const int rc = st.step();
    if (rc == SQLITE_DONE)
        return std::optional<SectionRecord>();
    if (rc != SQLITE_ROW)
        return sqlError(db_, file_, "next section");
    return std::optional<SectionRecord>(readSection(st));
}

Result<std::int64_t> Journal::recordCapture(CaptureRecord c) {
    std::lock_guard lock(mutex_);
    Transaction tx(db_);
    if (!tx.began())
        return sqlError(db_, file_, "begin");
    Statement cur(db_, "SELECT state, (SELECT COALESCE(MAX(attempt), 0) FROM captures WHERE "
                       "section_id = sections.id) FROM sections WHERE id = ?");
    cur.bind(1, c.sectionId);
    const int rc = cur.step();
    if (rc == SQLITE_DONE)
        return makeError(ErrorCode::NotFound, "no section " + std::to_string(c.sectionId));
    if (rc != SQLITE_ROW)
        return sqlError(db_, file_, "read section");
    const auto state = sectionStateFromString(cur.text(0));
    if (state != SectionState::Pending && state != SectionState::Rescan)
        return makeError(ErrorCode::InvalidArgument, "section " + std::to_string(c.sectionId) +
                                                         " is " + cur.text(0) +
                                                         ", not waiting for a capture");
    c.attempt = cur.i32(1) + 1;
    if (c.capturedUtc.empty())
        c.capturedUtc = nowUtc();
    Statement ins(db_,
                  "INSERT INTO captures (section_id, attempt, image_path, um_per_px, stage_x_um, "
                  "stage_y_um, stage_z_um, focus_score, focus_found, tiles, exposure_us, gain, "
                  "captured_utc) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?)");
    ins.bind(1, c.sectionId).bind(2, c.attempt).bind(3, c.imagePath).bind(4, c.umPerPx);
    ins.bind(5, c.stage.xUm).bind(6, c.stage.yUm).bind(7, c.stage.zUm).bind(8, c.focusScore);
    ins.bind(9, c.focusFound ? 1 : 0).bind(10, c.tiles).bind(11, c.exposureUs).bind(12, c.gain);
    ins.bind(13, c.capturedUtc);
    if (ins.step() != SQLITE_DONE)
        return sqlError(db_, file_, "insert capture");
    const std::int64_t id = sqlite3_last_insert_rowid(db_);
    Statement up(db_, "UPDATE sections SET state = 'captured', reason = '' WHERE id = ?");
    up.bind(1, c.sectionId);
    if (up.step() != SQLITE_DONE)
        return sqlError(db_, file_, "update section");
    if (!tx.commit())
        return sqlError(db_, file_, "commit capture");
    return id;
}

Result<std::vector<CaptureRecord>> Journal::captures(std::int64_t sectionId) {
    std::lock_guard lock(mutex_);
    Statement st(db_, (std::string("SELECT ") + kCaptureColumns +
                       " FROM captures WHERE section_id = ? ORDER BY attempt")
                          .c_str());
    st.bind(1, sectionId);
    return readAll<CaptureRecord>(st, db_, file_, "list captures", readCapture);
}

Result<CaptureRecord> Journal::capture(std::int64_t captureId) {
    std::lock_guard lock(mutex_);
    Statement st(
        db_, (std::string("SELECT ") + kCaptureColumns + " FROM captures WHERE id = ?").c_str());
    st.bind(1, captureId);
    return readOne<CaptureRecord>(st, db_, file_, "read capture",
                                  "no capture " + std::to_string(captureId), readCapture);
}

Result<std::optional<std::int64_t>> Journal::captureWithImage(const std::string& imagePath) {
    std::lock_guard lock(mutex_);
    Statement st(db_, "SELECT id FROM captures WHERE image_path = ? ORDER BY id LIMIT 1");
    st.bind(1, imagePath);
    const int rc = st.step();
    if (rc == SQLITE_DONE)
        return std::optional<std::int64_t>();
    if (rc != SQLITE_ROW)
        return sqlError(db_, file_, "find the capture of an image");
    return std::optional<std::int64_t>(st.i64(0));
}

Result<std::vector<std::int64_t>> Journal::capturesAwaitingRegistration() {
    std::lock_guard lock(mutex_);
    // The newest capture of every section that is still 'captured'.
    Statement st(db_, "SELECT c.id FROM captures c JOIN sections s ON s.id = c.section_id "
                      "WHERE s.state = 'captured' AND c.attempt = (SELECT MAX(attempt) FROM "
                      "captures WHERE section_id = s.id) AND NOT EXISTS (SELECT 1 FROM "
                      "registrations r WHERE r.capture_id = c.id) ORDER BY c.id");
    return readAll<std::int64_t>(st, db_, file_, "captures awaiting registration",
                                 [](const Statement& row) { return row.i64(0); });
}

Result<std::int64_t> Journal::recordRegistration(RegistrationRecord r) {
    std::lock_guard lock(mutex_);
    Transaction tx(db_);
    if (!tx.began())
        return sqlError(db_, file_, "begin");
    Statement cur(db_, "SELECT c.section_id, s.state FROM captures c JOIN sections s ON "
                       "s.id = c.section_id WHERE c.id = ?");
    cur.bind(1, r.captureId);
    const int rc = cur.step();
    if (rc == SQLITE_DONE)
        return makeError(ErrorCode::NotFound, "no capture " + std::to_string(r.captureId));
    if (rc != SQLITE_ROW)
        return sqlError(db_, file_, "read capture");
    const std::int64_t sectionId = cur.i64(0);
    if (r.registeredUtc.empty())
        r.registeredUtc = nowUtc();
    Statement ins(db_,
                  "INSERT INTO registrations (capture_id, atlas_slice, matched_slice, damaged, "
                  "damage_fraction, summary, warning, quality, result_path, overlay_path, "
                  "labels_path, result_json, registered_utc, damage_score, damage_verdict, "
                  "flag_score, planned_slice, planned_position_um, matched_position_um, "
                  "found_position_um, found_tilt_lr_deg, found_tilt_dv_deg) VALUES "
                  "(?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)");
    ins.bind(1, r.captureId).bind(2, r.atlasSlice).bind(3, r.matchedSlice);
    ins.bind(4, r.damaged ? 1 : 0).bind(5, r.damageFraction).bind(6, r.summary).bind(7, r.warning);
    ins.bind(8, r.quality).bind(9, r.resultPath).bind(10, r.overlayPath).bind(11, r.labelsPath);
    ins.bind(12, r.result.dump()).bind(13, r.registeredUtc).bind(14, r.damageScore);
    ins.bind(15, r.damageVerdict.empty() ? std::optional<std::string>()
                                         : std::optional<std::string>(r.damageVerdict));
    ins.bind(16, r.flagScore).bind(17, r.plannedSlice).bind(18, r.plannedPositionUm);
    ins.bind(19, r.matchedPositionUm).bind(20, r.foundPositionUm);
    ins.bind(21, r.foundTiltLrDeg).bind(22, r.foundTiltDvDeg);
    if (ins.step() != SQLITE_DONE)
        return sqlError(db_, file_, "insert registration");
    const std::int64_t id = sqlite3_last_insert_rowid(db_);
    if (r.series)
        if (auto s = writeSeries(id, *r.series); !s)
            return s.error();
    // Only a section still waiting for this registration changes state: a rescan requested in
    // the meantime wins.
    Statement up(db_,
                 "UPDATE sections SET state = ?, reason = '' WHERE id = ? AND state = 'captured'");
    up.bind(1, r.damaged ? "damaged" : "registered").bind(2, sectionId);
    if (up.step() != SQLITE_DONE)
        return sqlError(db_, file_, "update section");
    if (!tx.commit())
        return sqlError(db_, file_, "commit registration");
    return id;
}

Result<std::vector<RegistrationRecord>> Journal::registrations(std::int64_t sectionId) {
    std::lock_guard lock(mutex_);
    Statement st(db_, (std::string("SELECT ") + kRegistrationColumns +
                       " FROM registrations WHERE capture_id IN (SELECT id FROM captures WHERE "
                       "section_id = ?) ORDER BY id")
                          .c_str());
    st.bind(1, sectionId);
    return readAll<RegistrationRecord>(st, db_, file_, "list registrations", readRegistration);
}

Result<void> Journal::failSection(std::int64_t sectionId, const std::string& reason) {
    std::lock_guard lock(mutex_);
    Transaction tx(db_);
    if (!tx.began())
        return sqlError(db_, file_, "begin");
    Statement up(db_, "UPDATE sections SET state = 'failed', reason = ? WHERE id = ?");
    up.bind(1, reason).bind(2, sectionId);
    if (up.step() != SQLITE_DONE)
        return sqlError(db_, file_, "fail section");
    if (sqlite3_changes(db_) == 0)
        return makeError(ErrorCode::NotFound, "no section " + std::to_string(sectionId));
    if (!tx.commit())
        return sqlError(db_, file_, "commit");
    return {};
}

Result<void> Journal::requestRescan(std::int64_t sectionId) {
    std::lock_guard lock(mutex_);
    Transaction tx(db_);
    if (!tx.began())
        return sqlError(db_, file_, "begin");
    Statement cur(db_, "SELECT s.state, s.run_id, r.state FROM sections s JOIN runs r ON r.id = "
                       "s.run_id WHERE s.id = ?");
    cur.bind(1, sectionId);
    const int rc = cur.step();
    if (rc == SQLITE_DONE)
        return makeError(ErrorCode::NotFound, "no section " + std::to_string(sectionId));
    if (rc != SQLITE_ROW)
        return sqlError(db_, file_, "read section");
    const auto state = sectionStateFromString(cur.text(0));
    const std::int64_t runId = cur.i64(1);
    const auto runState = runStateFromString(cur.text(2));
    if (state == SectionState::Pending || state == SectionState::Captured ||
        state == SectionState::Rescan)
        return makeError(ErrorCode::InvalidArgument, "section " + std::to_string(sectionId) +
                                                         " is " + cur.text(0) +
                                                         "; only a registered, damaged or "
                                                         "failed section can be rescanned");
    if (runState == RunState::Cancelled)
        return makeError(ErrorCode::InvalidArgument,
                         "run " + std::to_string(runId) + " was cancelled; submit a new plan");
    Statement up(db_,
                 "UPDATE sections SET state = 'rescan', reason = 're-mounted, rescan requested' "
                 "WHERE id = ?");
    up.bind(1, sectionId);
    if (up.step() != SQLITE_DONE)
        return sqlError(db_, file_, "request rescan");
    if (runState == RunState::Finished || runState == RunState::Failed) {
        Statement reopen(db_, "UPDATE runs SET state = 'queued', reason = 'rescan requested', "
                              "ended_utc = '' WHERE id = ?");
        reopen.bind(1, runId);
        if (reopen.step() != SQLITE_DONE)
            return sqlError(db_, file_, "reopen run");
    }
    if (!tx.commit())
        return sqlError(db_, file_, "commit rescan");
    return {};
}

Result<void> Journal::checkIntegrity() {
    std::lock_guard lock(mutex_);
    {
        Statement st(db_, "PRAGMA integrity_check");
        if (st.step() != SQLITE_ROW)
            return sqlError(db_, file_, "integrity_check");
        if (st.text(0) != "ok")
            return makeError(ErrorCode::IoError,
                             "journal " + file_.string() + ": integrity_check: " + st.text(0));
    }
    Statement fk(db_, "PRAGMA foreign_key_check");
    const int rc = fk.step();
    if (rc == SQLITE_ROW)
        return makeError(ErrorCode::IoError, "journal " + file_.string() +
                                                 ": foreign_key_check: a row of " + fk.text(0) +
                                                 " references a missing " + fk.text(2));
    if (rc != SQLITE_DONE)
        return sqlError(db_, file_, "foreign_key_check");
    return {};
}

} // namespace slicestation::daemon
