// The journal's record of each registration's atlas plane (issue 19): schema version 3 and the
// series model's word on a section, which changes as later sections arrive.
#include "slicestation/daemon/storage/journal.hpp"

#include "journal_sql.hpp"

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using core::Result;
using namespace journal_sql;

// Version 3: the planned plane (the plan's slice and its position), the section's own match
// (matched_slice is version 1's; its refined position), the plane registered to, and the series
// model's word. Rows from older versions keep NULL: nobody recorded them.
const char* const journal_sql::kMigration3 = R"sql(
ALTER TABLE registrations ADD COLUMN planned_slice INTEGER;
ALTER TABLE registrations ADD COLUMN planned_position_um REAL;
ALTER TABLE registrations ADD COLUMN matched_position_um REAL;
ALTER TABLE registrations ADD COLUMN found_position_um REAL;
ALTER TABLE registrations ADD COLUMN series_position_um REAL;
ALTER TABLE registrations ADD COLUMN series_slot INTEGER;
ALTER TABLE registrations ADD COLUMN series_anomaly TEXT
    CHECK (series_anomaly IS NULL OR series_anomaly IN ('none','off-line','skipped-before',
           'swapped','out-of-order','duplicate','placed-on-line'));
ALTER TABLE registrations ADD COLUMN series_missing_before INTEGER;
ALTER TABLE registrations ADD COLUMN series_tilt_lr_deg REAL;
ALTER TABLE registrations ADD COLUMN series_tilt_dv_deg REAL;
)sql";

// Version 4: the tilt of the plane each section was registered to (0 for a stack's straight
// slice; the daemon registers to tilted planes once the run's tilt is found). NULL before.
const char* const journal_sql::kMigration4 = R"sql(
ALTER TABLE registrations ADD COLUMN found_tilt_lr_deg REAL;
ALTER TABLE registrations ADD COLUMN found_tilt_dv_deg REAL;
)sql";

Result<void> Journal::writeSeries(std::int64_t id, const SeriesPlacement& p) {
    Statement up(db_, "UPDATE registrations SET series_position_um = ?, series_slot = ?, "
                      "series_anomaly = ?, series_missing_before = ?, series_tilt_lr_deg = ?, "
                      "series_tilt_dv_deg = ? WHERE id = ?");
    up.bind(1, p.positionUm).bind(2, p.slot).bind(3, p.anomaly).bind(4, p.missingBefore);
    up.bind(5, p.tiltLrDeg).bind(6, p.tiltDvDeg).bind(7, id);
    if (up.step() != SQLITE_DONE) {
        if (sqlite3_errcode(db_) == SQLITE_CONSTRAINT)
            return makeError(ErrorCode::InvalidArgument, "journal " + file_.string() +
                                                             ": series anomaly \"" + p.anomaly +
                                                             "\" is not one the journal knows");
        return sqlError(db_, file_, "store the series placement");
    }
    if (sqlite3_changes(db_) == 0)
        return makeError(ErrorCode::NotFound, "no registration " + std::to_string(id));
    return {};
}

Result<void> Journal::updateSeries(std::int64_t registrationId, const SeriesPlacement& series) {
    std::lock_guard lock(mutex_);
    Transaction tx(db_);
    if (!tx.began())
        return sqlError(db_, file_, "begin");
    if (auto w = writeSeries(registrationId, series); !w)
        return w.error();
    if (!tx.commit())
        return sqlError(db_, file_, "commit series placement");
    return {};
}

} // namespace slicestation::daemon
