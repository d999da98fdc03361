#pragma once
// Private to http/: the API's resources, one file each, over the narrow station interface. Every
// handler answers errors through sendError (one status table: http_util.hpp).
#include "http_util.hpp"

#include "slicestation/daemon/station/station_api.hpp"

#include <httplib.h>

#include <memory>

namespace slicestation::daemon::http {

/// GET / (the page), /api/status, /api/live.jpg. routes_page.cpp
void addPageRoutes(httplib::Server& server, StationApi& station);
/// GET /api/runs, /api/runs/{id}, /api/runs/{id}/sections, /api/runs/{id}/export;
/// POST /api/runs, /api/runs/{id}/pause|resume|cancel. routes_runs.cpp
void addRunRoutes(httplib::Server& server, StationApi& station, const Authoriser& authorised);
/// GET /api/sections/{id}, .../image.jpg, .../overlay.png, .../region;
/// POST /api/sections/{id}/rescan. routes_sections.cpp
void addSectionRoutes(httplib::Server& server, StationApi& station, const Authoriser& authorised);
/// GET /api/alerts; POST /api/alerts/{id}/ack. routes_alerts.cpp
void addAlertRoutes(httplib::Server& server, StationApi& station, const Authoriser& authorised);

/// Station events fanned out to every event-stream client. routes_events.cpp
struct EventHub;
/// GET /api/events (Server-Sent Events), fed by a listener on `station`. \return the hub, for
/// closeEventStreams() at shutdown.
std::shared_ptr<EventHub> addEventRoutes(httplib::Server& server, StationApi& station);
/// Ends every event stream at once (so the server can stop) and refuses new ones.
void closeEventStreams(EventHub& hub) noexcept;

} // namespace slicestation::daemon::http
