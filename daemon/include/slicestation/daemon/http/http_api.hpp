#pragma once
/// The station's HTTP API (cpp-httplib), bound to 127.0.0.1 unless configured otherwise.
/// slicectl and the web page (GET /) talk to the daemon through it.
///
/// Read (JSON): GET /api/status, /api/runs, /api/runs/{id}, /api/runs/{id}/sections,
///   /api/runs/{id}/export?format=json|csv, /api/sections/{id}, /api/alerts[?open=1],
///   /api/sections/{id}/region?x=&y=[&of_width=W] (atlas region at a full-resolution pixel, or at
///   a pixel of the image scaled to width W), /api/damage/report?since=DATE&
///   target_false_alarm_rate=R, /api/damage/threshold (docs/damage.md).
/// The page: GET / (daemon/http/web/index.html, embedded; see docs/web.md).
/// Images (?width= 16..4096, never scaled up): GET /api/live.jpg (the latest camera frame),
///   /api/sections/{id}/image.jpg, /api/sections/{id}/overlay.png.
/// Events: GET /api/events, Server-Sent Events (section_captured, section_registered,
///   section_damaged, section_check_registration, section_failed, section_rescan, run_state,
///   alert_raised, alert_acknowledged, damage_threshold; data is JSON); a slow client loses its
///   oldest events, never slows the station. At most HttpLimits::kMaxEventStreams at once; past
///   them 503.
/// Control (need `Authorization: Bearer <token>`, else 401):
///   POST /api/runs (body: a plan, TOML or JSON), /api/runs/{id}/pause|resume|cancel,
///   /api/sections/{id}/rescan, /api/alerts/{id}/ack {"action": "rescan"|"accept"|text},
///   /api/damage/threshold {"flag_score": x | null}.
/// Errors: {"error": message} with 400 (bad request), 401, 404 (no such record), 405 (method),
/// 409 (wrong state), 411 (a body without Content-Length), 413 (body too large), 503 (too many
/// event streams or connections), 500 (a fault of the station, never of the request).
/// Hostile clients: every request's head and body are bounded in size and time before they are
/// read (HttpLimits); a POST is refused (401/411/413) before its body is read.
/// Errors map to statuses by one table (daemon/http/http_util.hpp, docs/architecture.md).
/// Layout: http_api.cpp wires the parts; http_server.cpp accepts and bounds connections;
/// one routes_*.cpp per resource, over StationApi (station/station_api.hpp) alone.
/// Threading: the server runs on its own threads (an acceptor and a pool of workers, one per
/// connection being served); stop() joins them.
#include "slicestation/core/result.hpp"
#include "slicestation/daemon/station/station_api.hpp"

#include <chrono>
#include <cstddef>
#include <memory>
#include <string>

namespace slicestation::daemon {

/// What the API takes from any client (docs/operation.md).
struct HttpLimits {
    static constexpr std::size_t kMaxBody = 1 << 20; ///< a request body, bytes (else 413)
    static constexpr std::size_t kMaxHead = 16
                                            << 10; ///< request line + headers, bytes (else cut off)
    static constexpr int kMaxEventStreams = 16;    ///< open /api/events at once (else 503)
    static constexpr int kWorkers = 64;            ///< connections served at once
    static constexpr int kMaxConnections = 128;   ///< open (served or waiting), else 503 and closed
    static constexpr int kKeepAliveRequests = 32; ///< requests on one connection
    static constexpr auto kIdle = std::chrono::seconds(5); ///< wait for a request (first or next)
    static constexpr auto kHeadDeadline =
        std::chrono::seconds(5); ///< head complete after its first byte
    static constexpr auto kBodyDeadline =
        std::chrono::seconds(10); ///< body complete after the head
    static constexpr auto kWriteStall =
        std::chrono::seconds(5); ///< a client that takes nothing this long is dropped
};

namespace http {
class BoundedServer;
struct EventHub;
} // namespace http

class HttpApi {
public:
    /// Binds (port 0: any free port) and starts serving `station` (borrowed: it must outlive
    /// the API). IoError when the address is taken, InvalidArgument for a port outside 0..65535.
    [[nodiscard]] static core::Result<std::unique_ptr<HttpApi>>
    start(StationApi& station, const std::string& bind, int port, std::string token);
    ~HttpApi();
    int port() const { return port_; }
    void stop() noexcept;

private:
    HttpApi() = default;
    std::shared_ptr<http::EventHub> events_;
    std::unique_ptr<http::BoundedServer> server_;
    int port_ = 0;
};

} // namespace slicestation::daemon
