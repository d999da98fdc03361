#include "slicestation/daemon/http/http_api.hpp"

#include "http_server.hpp"
#include "routes.hpp"

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;

core::Result<std::unique_ptr<HttpApi>> HttpApi::start(StationApi& station, const std::string& bind,
                                                      int port, std::string token) {
    if (port < 0 || port > 65535)
        return makeError(ErrorCode::InvalidArgument, "HTTP: port " + std::to_string(port));
    std::unique_ptr<HttpApi> api(new HttpApi());
    api->server_ = std::make_unique<http::BoundedServer>();
    auto& srv = *api->server_;
    // The connections, their timeouts and sizes are bounded by BoundedServer and Connection
    // (HttpLimits); these only make httplib's own checks and Keep-Alive header agree.
    srv.set_payload_max_length(HttpLimits::kMaxBody);
    srv.set_keep_alive_max_count(static_cast<std::size_t>(HttpLimits::kKeepAliveRequests));
    srv.set_keep_alive_timeout(
        std::chrono::duration_cast<std::chrono::seconds>(HttpLimits::kIdle).count());

    const http::Authoriser authorised = http::bearerAuthoriser(std::move(token));
    http::installAdmission(srv, authorised);
    http::addPageRoutes(srv, station);
    http::addRunRoutes(srv, station, authorised);
    http::addSectionRoutes(srv, station, authorised);
    http::addCountRoutes(srv, station);
    http::addAlertRoutes(srv, station, authorised);
    http::addDamageRoutes(srv, station, authorised);
    api->events_ = http::addEventRoutes(srv, station);
    srv.set_error_handler([](const httplib::Request&, httplib::Response& res) {
        if (res.body.empty())
            http::sendError(res, res.status,
                            res.status == 404 ? "no such endpoint" : "request failed");
    });
    srv.set_exception_handler(
        [](const httplib::Request&, httplib::Response& res, std::exception_ptr) {
            http::sendError(res, 500, "internal error");
        });

    auto bound = srv.bindTo(bind, port);
    if (!bound)
        return bound.error();
    api->port_ = *bound;
    if (auto r = srv.startServing(); !r)
        return r.error();
    return api;
}

HttpApi::~HttpApi() {
    stop();
}

void HttpApi::stop() noexcept {
    if (events_)
        http::closeEventStreams(*events_); // event streams end at once, so the server can stop
    if (server_)
        server_->stopServing();
}

} // namespace slicestation::daemon
