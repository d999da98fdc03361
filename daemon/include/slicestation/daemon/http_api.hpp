#pragma once
/// The station's HTTP API (cpp-httplib), bound to 127.0.0.1 unless configured otherwise.
/// slicectl and the web page (GET /) talk to the daemon through it.
///
/// Read (JSON): GET /api/status, /api/runs, /api/runs/{id}, /api/runs/{id}/sections,
///   /api/runs/{id}/export?format=json|csv, /api/sections/{id}, /api/alerts[?open=1],
///   /api/sections/{id}/region?x=&y=[&of_width=W] (atlas region at a full-resolution pixel, or at
///   a pixel of the image scaled to width W).
/// The page: GET / (daemon/web/index.html, embedded; see docs/web.md).
/// Images (?width= 16..4096, never scaled up): GET /api/live.jpg (the latest camera frame),
///   /api/sections/{id}/image.jpg, /api/sections/{id}/overlay.png.
/// Events: GET /api/events, Server-Sent Events (section_captured, section_registered,
///   section_damaged, section_failed, section_rescan, run_state, alert_raised,
///   alert_acknowledged; data is JSON); a slow client loses its oldest events, never slows the
///   station.
/// Control (need `Authorization: Bearer <token>`, else 401):
///   POST /api/runs (body: a plan, TOML or JSON), /api/runs/{id}/pause|resume|cancel,
///   /api/sections/{id}/rescan, /api/alerts/{id}/ack {"action": "rescan"|"accept"|text}.
/// Errors: {"error": message} with 400 (bad request), 401, 404 (no such record), 409 (wrong
/// state), 413 (body too large), 500.
/// Threading: the server runs on its own threads; stop() joins them.
#include "slicestation/core/result.hpp"
#include "slicestation/daemon/station.hpp"

#include <memory>
#include <string>
#include <thread>

namespace httplib {
class Server;
}

namespace slicestation::daemon {

class HttpApi {
public:
    /// Binds (port 0: any free port) and starts serving. IoError when the address is taken.
    [[nodiscard]] static core::Result<std::unique_ptr<HttpApi>> start(Station& station, const std::string& bind,
                                                                      int port, std::string token);
    ~HttpApi();
    int port() const { return port_; }
    void stop() noexcept;

private:
    HttpApi() = default;
    struct EventHub;
    std::shared_ptr<EventHub> events_;
    std::unique_ptr<httplib::Server> server_;
    std::thread thread_;
    int port_ = 0;
};

} // namespace slicestation::daemon
