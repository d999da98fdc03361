#pragma once
// Private to http/: the API's resources, one file each, over the narrow station interface. Every
// handler answers errors through sendError (one status table: http_util.hpp).
#include "http_util.hpp"

#include "slicestation/daemon/station/station_api.hpp"

#include <httplib.h>

#include <nlohmann/json.hpp>

#include <cstdint>
#include <memory>
#include <optional>

namespace slicestation::daemon::http {

/// GET / (the page), /api/status, /api/live.jpg. routes_page.cpp
void addPageRoutes(httplib::Server& server, StationApi& station);
/// GET /api/runs, /api/runs/{id}, /api/runs/{id}/sections, /api/runs/{id}/export;
/// POST /api/runs, /api/runs/{id}/pause|resume|cancel. routes_runs.cpp
void addRunRoutes(httplib::Server& server, StationApi& station, const Authoriser& authorised);
/// GET /api/sections/{id}, .../image.jpg, .../overlay.png, .../region, .../pyramid,
/// .../tiles/{level}/{x}_{y}.png;
/// POST /api/sections/{id}/rescan. routes_sections.cpp
void addSectionRoutes(httplib::Server& server, StationApi& station, const Authoriser& authorised);
/// GET /api/sections/{id}/counts, /api/runs/{id}/counts (CSV). routes_counts.cpp
void addCountRoutes(httplib::Server& server, StationApi& station);
/// GET /api/alerts; POST /api/alerts/{id}/ack. routes_alerts.cpp
void addAlertRoutes(httplib::Server& server, StationApi& station, const Authoriser& authorised);

/// GET /api/damage/report?since=&target_false_alarm_rate=, /api/damage/threshold;
/// POST /api/damage/threshold {"flag_score": x | null}. routes_damage.cpp
void addDamageRoutes(httplib::Server& server, StationApi& station, const Authoriser& authorised);

/// A POST on one record (/api/{things}/{id}/{verb}) after its common checks: authorised, the
/// id, and the optional JSON object body whose one key `key` (when given) passes `valid`.
struct ControlRequest {
    std::int64_t id = 0;
    nlohmann::json body = nlohmann::json::object(); ///< {} when the request has no body
};
/// \return the request, or nullopt once the refusal has been sent (401/403, 404 for a bad id,
/// 400 with `expected` for a bad body).
inline std::optional<ControlRequest>
controlRequest(const httplib::Request& req, httplib::Response& res, const Authoriser& authorised,
               const char* key = nullptr, bool (*valid)(const nlohmann::json&) = nullptr,
               const char* expected = "") {
    if (!authorised(req, res))
        return std::nullopt;
    auto id = idParam(req, res);
    if (!id)
        return std::nullopt;
    ControlRequest out{*id};
    if (key != nullptr && !req.body.empty()) {
        out.body = nlohmann::json::parse(req.body, nullptr, false);
        if (out.body.is_discarded() || !out.body.is_object() ||
            (out.body.contains(key) && !valid(out.body[key]))) {
            sendError(res, 400, expected);
            return std::nullopt;
        }
    }
    return out;
}

/// Station events fanned out to every event-stream client. routes_events.cpp
struct EventHub;
/// GET /api/events (Server-Sent Events), fed by a listener on `station`. \return the hub, for
/// closeEventStreams() at shutdown.
std::shared_ptr<EventHub> addEventRoutes(httplib::Server& server, StationApi& station);
/// Ends every event stream at once (so the server can stop) and refuses new ones.
void closeEventStreams(EventHub& hub) noexcept;

} // namespace slicestation::daemon::http
