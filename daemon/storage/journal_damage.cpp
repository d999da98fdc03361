// The journal's damage flags (for the lab's report) and the station settings it keeps.
#include "slicestation/daemon/storage/journal.hpp"

#include "journal_sql.hpp"

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using core::Result;
using namespace journal_sql;

Result<std::vector<DamageFlag>> Journal::damageFlags(const std::string& sinceUtc) {
    std::lock_guard lock(mutex_);
    // The registration a flag was raised for: the section's latest one journalled no later than
    // the alert (the worker records the registration, then raises the alert).
    constexpr const char* kFlagRegistration =
        "FROM registrations r JOIN captures c ON c.id = r.capture_id WHERE c.section_id = "
        "a.section_id AND r.registered_utc <= a.raised_utc ORDER BY r.id DESC LIMIT 1";
    Statement st(db_, (std::string("SELECT a.id, a.section_id, a.run_id, a.kind, a.raised_utc, "
                                   "a.acknowledged_utc, a.ack_action, s.name, s.slide_name, "
                                   "(SELECT r.damage_score ") +
                       kFlagRegistration + "), (SELECT r.flag_score " + kFlagRegistration +
                       ") FROM alerts a JOIN sections s ON s.id = a.section_id WHERE a.kind IN "
                       "('damaged','check_registration') AND a.raised_utc >= ? ORDER BY a.id")
                          .c_str());
    st.bind(1, sinceUtc);
    return readAll<DamageFlag>(
        st, db_, file_, "list damage flags", [this](const Statement& row) -> Result<DamageFlag> {
            DamageFlag f;
            f.alertId = row.i64(0);
            f.sectionId = row.i64(1);
            if (!row.isNull(2))
                f.runId = row.i64(2);
            auto kind = parseAlertKind(row.text(3));
            if (!kind)
                return makeError(ErrorCode::IoError, "journal " + file_.string() + ": alert " +
                                                         std::to_string(f.alertId) + ": " +
                                                         kind.error().message);
            f.kind = *kind;
            f.raisedUtc = row.text(4);
            if (!row.isNull(5))
                f.acknowledgedUtc = row.text(5);
            f.ackAction = row.text(6);
            f.sectionName = row.text(7);
            f.slideName = row.text(8);
            if (!row.isNull(9))
                f.damageScore = row.f64(9);
            if (!row.isNull(10))
                f.flagScore = row.f64(10);
            return f;
        });
}

Result<std::optional<Journal::Setting>> Journal::setting(const std::string& key) {
    std::lock_guard lock(mutex_);
    Statement st(db_, "SELECT value_json, set_utc FROM station_settings WHERE key = ?");
    st.bind(1, key);
    const int rc = st.step();
    if (rc == SQLITE_DONE)
        return std::optional<Setting>();
    if (rc != SQLITE_ROW)
        return sqlError(db_, file_, "read setting");
    auto value = nlohmann::json::parse(st.text(0), nullptr, false);
    if (value.is_discarded())
        return makeError(ErrorCode::IoError, "journal " + file_.string() + ": setting " + key +
                                                 ": stored value is not JSON");
    return std::optional<Setting>(Setting{std::move(value), st.text(1)});
}

Result<void> Journal::setSetting(const std::string& key, const nlohmann::json& value) {
    std::lock_guard lock(mutex_);
    Statement up(db_, "INSERT INTO station_settings (key, value_json, set_utc) VALUES (?,?,?) "
                      "ON CONFLICT(key) DO UPDATE SET value_json = excluded.value_json, "
                      "set_utc = excluded.set_utc");
    up.bind(1, key).bind(2, value.dump()).bind(3, nowUtc());
    if (up.step() != SQLITE_DONE)
        return sqlError(db_, file_, "store setting");
    return {};
}

Result<void> Journal::clearSetting(const std::string& key) {
    std::lock_guard lock(mutex_);
    Statement del(db_, "DELETE FROM station_settings WHERE key = ?");
    del.bind(1, key);
    if (del.step() != SQLITE_DONE)
        return sqlError(db_, file_, "clear setting");
    return {};
}

} // namespace slicestation::daemon
