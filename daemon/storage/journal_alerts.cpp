// The journal's alerts: raised, listed, acknowledged.
#include "slicestation/daemon/storage/journal.hpp"

#include "journal_sql.hpp"

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using core::Result;
using namespace journal_sql;

Result<std::int64_t> Journal::raiseAlert(AlertRecord a) {
    std::lock_guard lock(mutex_);
    if (a.raisedUtc.empty())
        a.raisedUtc = nowUtc();
    Statement ins(db_,
                  "INSERT INTO alerts (run_id, section_id, kind, severity, message, raised_utc) "
                  "VALUES (?,?,?,?,?,?)");
    ins.bind(1, a.runId)
        .bind(2, a.sectionId)
        .bind(3, toString(a.kind))
        .bind(4, toString(a.severity));
    ins.bind(5, a.message).bind(6, a.raisedUtc);
    if (ins.step() != SQLITE_DONE)
        return sqlError(db_, file_, "insert alert");
    return static_cast<std::int64_t>(sqlite3_last_insert_rowid(db_));
}

Result<std::vector<AlertRecord>> Journal::alerts(bool openOnly) {
    std::lock_guard lock(mutex_);
    Statement st(db_, (std::string("SELECT ") + kAlertColumns + " FROM alerts" +
                       (openOnly ? " WHERE acknowledged_utc IS NULL" : "") + " ORDER BY id")
                          .c_str());
    return readAll<AlertRecord>(st, db_, file_, "list alerts",
                                [this](const Statement& row) { return readAlert(row, file_); });
}

Result<AlertRecord> Journal::alert(std::int64_t alertId) {
    std::lock_guard lock(mutex_);
    Statement st(db_,
                 (std::string("SELECT ") + kAlertColumns + " FROM alerts WHERE id = ?").c_str());
    st.bind(1, alertId);
    return readOne<AlertRecord>(st, db_, file_, "read alert", "no alert " + std::to_string(alertId),
                                [this](const Statement& row) { return readAlert(row, file_); });
}

Result<AlertRecord> Journal::acknowledgeAlert(std::int64_t alertId, const std::string& action) {
    {
        std::lock_guard lock(mutex_);
        Statement up(db_, "UPDATE alerts SET acknowledged_utc = ?, ack_action = ? WHERE id = ? AND "
                          "acknowledged_utc IS NULL");
        up.bind(1, nowUtc()).bind(2, action).bind(3, alertId);
        if (up.step() != SQLITE_DONE)
            return sqlError(db_, file_, "acknowledge alert");
        if (sqlite3_changes(db_) == 0) {
            Statement st(db_, "SELECT 1 FROM alerts WHERE id = ?");
            st.bind(1, alertId);
            if (st.step() != SQLITE_ROW)
                return makeError(ErrorCode::NotFound, "no alert " + std::to_string(alertId));
            return makeError(ErrorCode::InvalidArgument,
                             "alert " + std::to_string(alertId) + " is already acknowledged");
        }
    }
    return alert(alertId);
}

} // namespace slicestation::daemon
