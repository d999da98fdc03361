#pragma once
// Private to storage/: the journal's SQLite helpers (statements, transactions, errors) and the
// readers of its rows into records.
#include "slicestation/daemon/storage/journal.hpp"

#include <sqlite3.h>

#include <cerrno>
#include <filesystem>
#include <string>
#include <utility>

namespace slicestation::daemon::journal_sql {

using core::ErrorCode;
using core::makeError;

/// The last error of `db`. A full disk (SQLITE_FULL) carries sysErrno ENOSPC, like a failed
/// image write, so that callers treat both alike.
inline core::Error sqlError(sqlite3* db, const std::filesystem::path& file, const char* what) {
    const int err = sqlite3_errcode(db) == SQLITE_FULL ? ENOSPC : 0;
    return makeError(
        ErrorCode::IoError,
        std::string("journal ") + file.string() + ": " + what + ": " + sqlite3_errmsg(db), err);
}

/// A prepared statement; finalised on destruction. Bind indices start at 1.
class Statement {
public:
    Statement(sqlite3* db, const char* sql) {
        if (sqlite3_prepare_v2(db, sql, -1, &stmt_, nullptr) != SQLITE_OK)
            stmt_ = nullptr;
    }
    ~Statement() { sqlite3_finalize(stmt_); }
    Statement(const Statement&) = delete;
    Statement& operator=(const Statement&) = delete;
    bool ok() const { return stmt_ != nullptr; }

    Statement& bind(int i, std::int64_t v) {
        sqlite3_bind_int64(stmt_, i, v);
        return *this;
    }
    Statement& bind(int i, int v) {
        sqlite3_bind_int64(stmt_, i, v);
        return *this;
    }
    Statement& bind(int i, double v) {
        sqlite3_bind_double(stmt_, i, v);
        return *this;
    }
    Statement& bind(int i, const std::string& v) {
        sqlite3_bind_text(stmt_, i, v.c_str(), static_cast<int>(v.size()), SQLITE_TRANSIENT);
        return *this;
    }
    Statement& bind(int i, const char* v) { return bind(i, std::string(v)); }
    template <class T> Statement& bind(int i, const std::optional<T>& v) {
        if (v)
            return bind(i, *v);
        sqlite3_bind_null(stmt_, i);
        return *this;
    }
    /// SQLITE_ROW, SQLITE_DONE or an error code.
    int step() { return sqlite3_step(stmt_); }

    std::int64_t i64(int c) const { return sqlite3_column_int64(stmt_, c); }
    int i32(int c) const { return sqlite3_column_int(stmt_, c); }
    double f64(int c) const { return sqlite3_column_double(stmt_, c); }
    bool isNull(int c) const { return sqlite3_column_type(stmt_, c) == SQLITE_NULL; }
    std::string text(int c) const {
        const auto* p = sqlite3_column_text(stmt_, c);
        return p ? std::string(reinterpret_cast<const char*>(p)) : std::string();
    }

private:
    sqlite3_stmt* stmt_ = nullptr;
};

/// BEGIN IMMEDIATE on construction, ROLLBACK on destruction unless commit() succeeded.
class Transaction {
public:
    explicit Transaction(sqlite3* db) : db_(db) {
        began_ = sqlite3_exec(db_, "BEGIN IMMEDIATE", nullptr, nullptr, nullptr) == SQLITE_OK;
    }
    ~Transaction() {
        if (began_ && !committed_)
            sqlite3_exec(db_, "ROLLBACK", nullptr, nullptr, nullptr);
    }
    Transaction(const Transaction&) = delete;
    Transaction& operator=(const Transaction&) = delete;
    bool began() const { return began_; }
    bool commit() {
        committed_ = sqlite3_exec(db_, "COMMIT", nullptr, nullptr, nullptr) == SQLITE_OK;
        return committed_;
    }

private:
    sqlite3* db_;
    bool began_ = false;
    bool committed_ = false;
};

inline nlohmann::json parseJsonColumn(const std::string& text) {
    auto j = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
    return j.is_discarded() ? nlohmann::json() : j;
}

constexpr const char* kRunColumns =
    "r.id, r.name, r.state, r.reason, r.plan_json, r.settings_json, r.created_utc, r.started_utc, "
    "r.ended_utc, (SELECT COUNT(*) FROM sections s WHERE s.run_id = r.id), "
    "(SELECT COUNT(*) FROM sections s WHERE s.run_id = r.id AND s.state IN "
    "('registered','damaged','failed'))";

inline RunRecord readRun(const Statement& st) {
    RunRecord r;
    r.id = st.i64(0);
    r.name = st.text(1);
    r.state = runStateFromString(st.text(2)).value_or(RunState::Failed);
    r.reason = st.text(3);
    r.plan = parseJsonColumn(st.text(4));
    r.settings = parseJsonColumn(st.text(5));
    r.createdUtc = st.text(6);
    r.startedUtc = st.text(7);
    r.endedUtc = st.text(8);
    r.sectionCount = st.i32(9);
    r.doneCount = st.i32(10);
    return r;
}

constexpr const char* kSectionColumns =
    "s.id, s.run_id, s.slide_index, s.slide_name, s.idx, s.name, s.x_um, s.y_um, s.width_um, "
    "s.height_um, s.expected_slice, s.state, s.reason, "
    "(SELECT COUNT(*) FROM captures c WHERE c.section_id = s.id), "
    "(SELECT r.damage_score FROM registrations r JOIN captures c ON c.id = r.capture_id "
    "WHERE c.section_id = s.id ORDER BY r.id DESC LIMIT 1), "
    "(SELECT r.damage_verdict FROM registrations r JOIN captures c ON c.id = r.capture_id "
    "WHERE c.section_id = s.id ORDER BY r.id DESC LIMIT 1)";

inline SectionRecord readSection(const Statement& st) {
    SectionRecord s;
    s.id = st.i64(0);
    s.runId = st.i64(1);
    s.slideIndex = st.i32(2);
    s.slideName = st.text(3);
    s.index = st.i32(4);
    s.name = st.text(5);
    s.xUm = st.f64(6);
    s.yUm = st.f64(7);
    s.widthUm = st.f64(8);
    s.heightUm = st.f64(9);
    if (!st.isNull(10))
        s.expectedSlice = st.i32(10);
    s.state = sectionStateFromString(st.text(11)).value_or(SectionState::Failed);
    s.reason = st.text(12);
    s.attempts = st.i32(13);
    if (!st.isNull(14))
        s.damageScore = st.f64(14);
    s.damageVerdict = st.text(15);
    return s;
}

constexpr const char* kCaptureColumns =
    "id, section_id, attempt, image_path, um_per_px, stage_x_um, stage_y_um, stage_z_um, "
    "focus_score, focus_found, tiles, exposure_us, gain, captured_utc";

inline CaptureRecord readCapture(const Statement& st) {
    CaptureRecord c;
    c.id = st.i64(0);
    c.sectionId = st.i64(1);
    c.attempt = st.i32(2);
    c.imagePath = st.text(3);
    c.umPerPx = st.f64(4);
    c.stage = {st.f64(5), st.f64(6), st.f64(7)};
    if (!st.isNull(8))
        c.focusScore = st.f64(8);
    c.focusFound = st.i32(9) != 0;
    c.tiles = st.i32(10);
    c.exposureUs = st.i64(11);
    c.gain = st.f64(12);
    c.capturedUtc = st.text(13);
    return c;
}

constexpr const char* kRegistrationColumns =
    "id, capture_id, atlas_slice, matched_slice, damaged, damage_fraction, summary, warning, "
    "quality, result_path, overlay_path, labels_path, result_json, registered_utc, damage_score, "
    "damage_verdict, flag_score, planned_slice, planned_position_um, matched_position_um, "
    "found_position_um, series_position_um, series_slot, series_anomaly, series_missing_before, "
    "series_tilt_lr_deg, series_tilt_dv_deg, found_tilt_lr_deg, found_tilt_dv_deg";

/// Schema version 3 (journal_series.cpp): the planes of every registration.
extern const char* const kMigration3;
/// Schema version 4 (journal_series.cpp): the tilt of the plane registered to.
extern const char* const kMigration4;

inline std::optional<double> optionalF64(const Statement& st, int c) {
    return st.isNull(c) ? std::nullopt : std::optional<double>(st.f64(c));
}

inline RegistrationRecord readRegistration(const Statement& st) {
    RegistrationRecord r;
    r.id = st.i64(0);
    r.captureId = st.i64(1);
    r.atlasSlice = st.i32(2);
    if (!st.isNull(3))
        r.matchedSlice = st.i32(3);
    r.damaged = st.i32(4) != 0;
    r.damageFraction = st.f64(5);
    r.summary = st.text(6);
    r.warning = st.text(7);
    r.quality = st.f64(8);
    r.resultPath = st.text(9);
    r.overlayPath = st.text(10);
    r.labelsPath = st.text(11);
    r.result = parseJsonColumn(st.text(12));
    r.registeredUtc = st.text(13);
    if (!st.isNull(14))
        r.damageScore = st.f64(14);
    r.damageVerdict = st.text(15);
    if (!st.isNull(16))
        r.flagScore = st.f64(16);
    if (!st.isNull(17))
        r.plannedSlice = st.i32(17);
    r.plannedPositionUm = optionalF64(st, 18);
    r.matchedPositionUm = optionalF64(st, 19);
    r.foundPositionUm = optionalF64(st, 20);
    if (!st.isNull(21)) {
        SeriesPlacement p;
        p.positionUm = st.f64(21);
        p.slot = st.i32(22);
        p.anomaly = st.text(23);
        p.missingBefore = st.i32(24);
        p.tiltLrDeg = st.f64(25);
        p.tiltDvDeg = st.f64(26);
        r.series = p;
    }
    r.foundTiltLrDeg = optionalF64(st, 27);
    r.foundTiltDvDeg = optionalF64(st, 28);
    return r;
}

/// Every row of `st` through `read` (a record, or a Result of one); a failed step is the
/// journal's error for `what`.
template <class Record, class Read>
core::Result<std::vector<Record>> readAll(Statement& st, sqlite3* db,
                                          const std::filesystem::path& file, const char* what,
                                          Read read) {
    std::vector<Record> out;
    int rc;
    while ((rc = st.step()) == SQLITE_ROW) {
        core::Result<Record> r = read(st);
        if (!r)
            return r.error();
        out.push_back(std::move(*r));
    }
    if (rc != SQLITE_DONE)
        return sqlError(db, file, what);
    return out;
}

/// The one row of `st` through `read`; NotFound with `missing` when there is none.
template <class Record, class Read>
core::Result<Record> readOne(Statement& st, sqlite3* db, const std::filesystem::path& file,
                             const char* what, const std::string& missing, Read read) {
    const int rc = st.step();
    if (rc == SQLITE_DONE)
        return makeError(ErrorCode::NotFound, missing);
    if (rc != SQLITE_ROW)
        return sqlError(db, file, what);
    return read(st);
}

constexpr const char* kAlertColumns =
    "id, run_id, section_id, kind, severity, message, raised_utc, acknowledged_utc, ack_action";

/// An alert row; a kind or severity this build does not know (a newer daemon's journal, an edited
/// file) is an IoError naming it and the alert, never read as another one.
inline core::Result<AlertRecord> readAlert(const Statement& st, const std::filesystem::path& file) {
    AlertRecord a;
    a.id = st.i64(0);
    if (!st.isNull(1))
        a.runId = st.i64(1);
    if (!st.isNull(2))
        a.sectionId = st.i64(2);
    auto kind = parseAlertKind(st.text(3));
    auto severity = parseAlertSeverity(st.text(4));
    if (!kind || !severity)
        return makeError(ErrorCode::IoError,
                         "journal " + file.string() + ": alert " + std::to_string(a.id) + ": " +
                             (kind ? severity.error().message : kind.error().message));
    a.kind = *kind;
    a.severity = *severity;
    a.message = st.text(5);
    a.raisedUtc = st.text(6);
    if (!st.isNull(7))
        a.acknowledgedUtc = st.text(7);
    a.ackAction = st.text(8);
    return a;
}

} // namespace slicestation::daemon::journal_sql
