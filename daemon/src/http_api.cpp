#include "slicestation/daemon/http_api.hpp"

#include "slicestation/daemon/config_document.hpp"

#include <httplib.h>

#include <charconv>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;

namespace {

constexpr std::size_t kMaxBody = 1 << 20; // a plan of thousands of sections fits in far less

int httpStatus(const core::Error& e) {
    switch (e.code) {
    case ErrorCode::InvalidArgument:
    case ErrorCode::OutOfRange:
    case ErrorCode::Unsupported: return 400;
    case ErrorCode::NotFound: return 404;
    default: return 500;
    }
}

void sendJson(httplib::Response& res, const nlohmann::json& j, int status = 200) {
    res.status = status;
    res.set_content(j.dump(), "application/json");
}

void sendError(httplib::Response& res, int status, const std::string& message) {
    sendJson(res, {{"error", message}}, status);
}

void sendError(httplib::Response& res, const core::Error& e) { sendError(res, httpStatus(e), e.message); }

/// The numeric id in path capture 1; 400 for anything else (no path reaches a file).
std::optional<std::int64_t> idParam(const httplib::Request& req, httplib::Response& res) {
    const std::string s = req.matches.size() > 1 ? std::string(req.matches[1]) : std::string();
    std::int64_t v = 0;
    const auto [p, ec] = std::from_chars(s.data(), s.data() + s.size(), v);
    if (ec != std::errc() || p != s.data() + s.size() || v <= 0) {
        sendError(res, 400, "bad id \"" + s + "\"");
        return std::nullopt;
    }
    return v;
}

} // namespace

core::Result<std::unique_ptr<HttpApi>> HttpApi::start(Station& station, const std::string& bind, int port,
                                                      std::string token) {
    std::unique_ptr<HttpApi> api(new HttpApi());
    api->server_ = std::make_unique<httplib::Server>();
    auto& srv = *api->server_;
    srv.set_payload_max_length(kMaxBody);
    srv.set_read_timeout(10, 0);
    srv.set_write_timeout(10, 0);

    // Control requests need the bearer token; without a configured token they are refused.
    auto authorised = [token](const httplib::Request& req, httplib::Response& res) {
        if (token.empty()) {
            sendError(res, 401, "control is disabled: no daemon.token configured");
            return false;
        }
        const std::string expected = "Bearer " + token;
        const std::string got = req.get_header_value("Authorization");
        // Constant-time comparison: the token is a secret.
        bool same = got.size() == expected.size();
        unsigned char diff = 0;
        for (std::size_t i = 0; i < expected.size(); ++i)
            diff |= static_cast<unsigned char>(expected[i] ^ (i < got.size() ? got[i] : 0));
        if (!same || diff != 0) {
            res.set_header("WWW-Authenticate", "Bearer");
            sendError(res, 401, "missing or wrong bearer token");
            return false;
        }
        return true;
    };
    Station* st = &station;

    srv.Get("/api/status", [st](const httplib::Request&, httplib::Response& res) { sendJson(res, st->status()); });
    srv.Get("/api/runs", [st](const httplib::Request&, httplib::Response& res) {
        auto runs = st->journal().runs();
        if (!runs) return sendError(res, runs.error());
        nlohmann::json j = nlohmann::json::array();
        for (const auto& r : *runs) j.push_back(toJson(r));
        sendJson(res, j);
    });
    srv.Get(R"(/api/runs/([^/]+))", [st](const httplib::Request& req, httplib::Response& res) {
        auto id = idParam(req, res);
        if (!id) return;
        auto r = st->journal().run(*id);
        if (!r) return sendError(res, r.error());
        nlohmann::json j = toJson(*r);
        j["plan"] = r->plan;
        sendJson(res, j);
    });
    srv.Get(R"(/api/runs/([^/]+)/sections)", [st](const httplib::Request& req, httplib::Response& res) {
        auto id = idParam(req, res);
        if (!id) return;
        if (auto r = st->journal().run(*id); !r) return sendError(res, r.error());
        auto secs = st->journal().sections(*id);
        if (!secs) return sendError(res, secs.error());
        nlohmann::json j = nlohmann::json::array();
        for (const auto& s : *secs) j.push_back(toJson(s));
        sendJson(res, j);
    });
    srv.Get(R"(/api/runs/([^/]+)/export)", [st](const httplib::Request& req, httplib::Response& res) {
        auto id = idParam(req, res);
        if (!id) return;
        const std::string format = req.has_param("format") ? req.get_param_value("format") : "json";
        auto out = st->exportRun(*id, format);
        if (!out) return sendError(res, out.error());
        res.set_content(*out, format == "csv" ? "text/csv" : "application/json");
    });
    srv.Get(R"(/api/sections/([^/]+))", [st](const httplib::Request& req, httplib::Response& res) {
        auto id = idParam(req, res);
        if (!id) return;
        auto d = st->sectionDetail(*id);
        if (!d) return sendError(res, d.error());
        sendJson(res, *d);
    });
    srv.Get("/api/alerts", [st](const httplib::Request& req, httplib::Response& res) {
        const bool open = req.has_param("open") && req.get_param_value("open") != "0";
        auto a = st->journal().alerts(open);
        if (!a) return sendError(res, a.error());
        nlohmann::json j = nlohmann::json::array();
        for (const auto& x : *a) j.push_back(toJson(x));
        sendJson(res, j);
    });

    srv.Post("/api/runs", [st, authorised](const httplib::Request& req, httplib::Response& res) {
        if (!authorised(req, res)) return;
        const std::string type = req.get_header_value("Content-Type");
        const bool json = type.find("json") != std::string::npos ||
                          (type.find("toml") == std::string::npos && !req.body.empty() &&
                           req.body[req.body.find_first_not_of(" \t\r\n") == std::string::npos
                                        ? 0
                                        : req.body.find_first_not_of(" \t\r\n")] == '{');
        auto doc = parseDocument(req.body, json ? DocumentFormat::Json : DocumentFormat::Toml, "plan");
        if (!doc) return sendError(res, 400, doc.error().message);
        auto id = st->submitPlan(*doc, "plan");
        if (!id) return sendError(res, 400, id.error().message);
        sendJson(res, {{"run_id", *id}}, 201);
    });
    auto control = [&srv, st, authorised](const char* pattern, auto action) {
        srv.Post(pattern, [st, authorised, action](const httplib::Request& req, httplib::Response& res) {
            if (!authorised(req, res)) return;
            auto id = idParam(req, res);
            if (!id) return;
            core::Result<void> r = action(*st, *id);
            if (!r) {
                const int code = r.error().code == ErrorCode::NotFound ? 404
                                 : r.error().code == ErrorCode::InvalidArgument ? 409
                                                                                 : 500;
                return sendError(res, code, r.error().message);
            }
            sendJson(res, {{"ok", true}});
        });
    };
    control(R"(/api/runs/([^/]+)/pause)", [](Station& s, std::int64_t id) { return s.scanner().pause(id); });
    srv.Post(R"(/api/runs/([^/]+)/resume)", [st, authorised](const httplib::Request& req, httplib::Response& res) {
        if (!authorised(req, res)) return;
        auto id = idParam(req, res);
        if (!id) return;
        bool resetAlarm = false;
        if (!req.body.empty()) {
            auto j = nlohmann::json::parse(req.body, nullptr, false);
            if (j.is_discarded() || !j.is_object() || (j.contains("reset_stage_alarm") && !j["reset_stage_alarm"].is_boolean()))
                return sendError(res, 400, "body: expected {\"reset_stage_alarm\": true | false}");
            resetAlarm = j.value("reset_stage_alarm", false);
        }
        auto r = st->scanner().resume(*id, resetAlarm);
        if (!r)
            return sendError(res, r.error().code == ErrorCode::NotFound ? 404
                                  : r.error().code == ErrorCode::InvalidArgument ? 409 : 500,
                             r.error().message);
        sendJson(res, {{"ok", true}});
    });
    control(R"(/api/runs/([^/]+)/cancel)", [](Station& s, std::int64_t id) { return s.scanner().cancel(id); });
    control(R"(/api/sections/([^/]+)/rescan)", [](Station& s, std::int64_t id) { return s.requestRescan(id); });
    srv.Post(R"(/api/alerts/([^/]+)/ack)", [st, authorised](const httplib::Request& req, httplib::Response& res) {
        if (!authorised(req, res)) return;
        auto id = idParam(req, res);
        if (!id) return;
        std::string action = "accept";
        if (!req.body.empty()) {
            auto j = nlohmann::json::parse(req.body, nullptr, false);
            if (j.is_discarded() || !j.is_object() || (j.contains("action") && !j["action"].is_string()))
                return sendError(res, 400, "body: expected {\"action\": \"rescan\" | \"accept\" | text}");
            action = j.value("action", action);
        }
        auto alert = st->journal().alert(*id);
        if (!alert) return sendError(res, alert.error());
        if (action == "rescan") {
            if (!alert->sectionId) return sendError(res, 409, "alert " + std::to_string(*id) + " concerns no section");
            if (auto r = st->requestRescan(*alert->sectionId); !r) return sendError(res, 409, r.error().message);
        }
        auto a = st->notifier().acknowledge(*id, action);
        if (!a) return sendError(res, a.error().code == ErrorCode::NotFound ? 404 : 409, a.error().message);
        sendJson(res, toJson(*a));
    });
    srv.set_error_handler([](const httplib::Request&, httplib::Response& res) {
        if (res.body.empty()) sendError(res, res.status, res.status == 404 ? "no such endpoint" : "request failed");
    });
    srv.set_exception_handler([](const httplib::Request&, httplib::Response& res, std::exception_ptr) {
        sendError(res, 500, "internal error");
    });

    if (port == 0) {
        api->port_ = srv.bind_to_any_port(bind.c_str());
        if (api->port_ < 0) return makeError(ErrorCode::IoError, "HTTP: cannot bind " + bind);
    } else {
        if (!srv.bind_to_port(bind.c_str(), port))
            return makeError(ErrorCode::IoError, "HTTP: cannot bind " + bind + ":" + std::to_string(port) +
                                                     " (in use, or not an address of this machine)");
        api->port_ = port;
    }
    api->thread_ = std::thread([&srv] { srv.listen_after_bind(); });
    return api;
}

HttpApi::~HttpApi() { stop(); }

void HttpApi::stop() noexcept {
    if (server_) server_->stop();
    if (thread_.joinable()) thread_.join();
}

} // namespace slicestation::daemon
