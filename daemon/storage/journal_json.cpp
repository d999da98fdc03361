// The journal's records as JSON, for the API, events and exports.
#include "slicestation/daemon/storage/journal.hpp"

namespace slicestation::daemon {

nlohmann::json toJson(const RunRecord& r) {
    return {{"id", r.id},
            {"name", r.name},
            {"state", toString(r.state)},
            {"reason", r.reason},
            {"created_utc", r.createdUtc},
            {"started_utc", r.startedUtc},
            {"ended_utc", r.endedUtc},
            {"sections", r.sectionCount},
            {"done", r.doneCount},
            {"settings", r.settings}};
}

nlohmann::json toJson(const SectionRecord& s) {
    nlohmann::json j{{"id", s.id},
                     {"run_id", s.runId},
                     {"slide_index", s.slideIndex},
                     {"slide", s.slideName},
                     {"index", s.index},
                     {"name", s.name},
                     {"x_um", s.xUm},
                     {"y_um", s.yUm},
                     {"width_um", s.widthUm},
                     {"height_um", s.heightUm},
                     {"state", toString(s.state)},
                     {"reason", s.reason},
                     {"attempts", s.attempts}};
    j["expected_slice"] = s.expectedSlice ? nlohmann::json(*s.expectedSlice) : nlohmann::json();
    j["damage_score"] = s.damageScore ? nlohmann::json(*s.damageScore) : nlohmann::json();
    j["damage_verdict"] =
        s.damageVerdict.empty() ? nlohmann::json() : nlohmann::json(s.damageVerdict);
    return j;
}

nlohmann::json toJson(const CaptureRecord& c) {
    nlohmann::json j{
        {"id", c.id},
        {"section_id", c.sectionId},
        {"attempt", c.attempt},
        {"image", c.imagePath},
        {"um_per_px", c.umPerPx},
        {"stage", {{"x_um", c.stage.xUm}, {"y_um", c.stage.yUm}, {"z_um", c.stage.zUm}}},
        {"focus_found", c.focusFound},
        {"tiles", c.tiles},
        {"exposure_us", c.exposureUs},
        {"gain", c.gain},
        {"captured_utc", c.capturedUtc}};
    j["focus_score"] = c.focusScore ? nlohmann::json(*c.focusScore) : nlohmann::json();
    return j;
}

nlohmann::json toJson(const RegistrationRecord& r) {
    nlohmann::json j{{"id", r.id},
                     {"capture_id", r.captureId},
                     {"atlas_slice", r.atlasSlice},
                     {"damaged", r.damaged},
                     {"damage_fraction", r.damageFraction},
                     {"damage_summary", r.summary},
                     {"warning", r.warning},
                     {"quality", r.quality},
                     {"result", r.resultPath},
                     {"overlay", r.overlayPath},
                     {"labels", r.labelsPath},
                     {"registered_utc", r.registeredUtc}};
    j["matched_slice"] = r.matchedSlice ? nlohmann::json(*r.matchedSlice) : nlohmann::json();
    j["damage_score"] = r.damageScore ? nlohmann::json(*r.damageScore) : nlohmann::json();
    j["damage_verdict"] =
        r.damageVerdict.empty() ? nlohmann::json() : nlohmann::json(r.damageVerdict);
    j["flag_score"] = r.flagScore ? nlohmann::json(*r.flagScore) : nlohmann::json();
    j["plane"] = planeJson(r);
    return j;
}

nlohmann::json planeJson(const RegistrationRecord& r) {
    const auto slicePlane = [](std::optional<int> slice, std::optional<double> positionUm) {
        if (!slice && !positionUm)
            return nlohmann::json();
        return nlohmann::json{
            {"slice", slice ? nlohmann::json(*slice) : nlohmann::json()},
            {"position_um", positionUm ? nlohmann::json(*positionUm) : nlohmann::json()}};
    };
    nlohmann::json j;
    j["planned"] = slicePlane(r.plannedSlice, r.plannedPositionUm);
    j["matched"] = slicePlane(r.matchedSlice, r.matchedPositionUm);
    // The plane registered to: a stack slice, or the plane through its position cut at the run's
    // found tilt (unknown, null, for registrations journalled before schema version 4).
    j["found"] = slicePlane(r.atlasSlice, r.foundPositionUm);
    if (r.foundTiltLrDeg && r.foundTiltDvDeg) {
        j["found"]["tilt_lr_deg"] = *r.foundTiltLrDeg;
        j["found"]["tilt_dv_deg"] = *r.foundTiltDvDeg;
        j["found"]["tilted"] = *r.foundTiltLrDeg != 0 || *r.foundTiltDvDeg != 0;
    } else {
        j["found"]["tilt_lr_deg"] = j["found"]["tilt_dv_deg"] = nullptr;
        j["found"]["tilted"] = false;
    }
    if (r.series)
        j["series"] = {
            {"position_um", r.series->positionUm}, {"slot", r.series->slot},
            {"anomaly", r.series->anomaly},        {"missing_before", r.series->missingBefore},
            {"tilt_lr_deg", r.series->tiltLrDeg},  {"tilt_dv_deg", r.series->tiltDvDeg}};
    else
        j["series"] = nullptr;
    return j;
}

nlohmann::json toJson(const AlertRecord& a) {
    nlohmann::json j{
        {"id", a.id},           {"kind", toString(a.kind)},  {"severity", toString(a.severity)},
        {"message", a.message}, {"raised_utc", a.raisedUtc}, {"ack_action", a.ackAction}};
    j["run_id"] = a.runId ? nlohmann::json(*a.runId) : nlohmann::json();
    j["section_id"] = a.sectionId ? nlohmann::json(*a.sectionId) : nlohmann::json();
    j["acknowledged_utc"] =
        a.acknowledgedUtc ? nlohmann::json(*a.acknowledgedUtc) : nlohmann::json();
    j["open"] = !a.acknowledgedUtc.has_value();
    return j;
}

} // namespace slicestation::daemon
