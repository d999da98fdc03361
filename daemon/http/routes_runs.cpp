// Runs: the list, one run, its sections, its export; submitting a plan; pause, resume, cancel.
#include "routes.hpp"

#include "slicestation/daemon/config/config_document.hpp"

namespace slicestation::daemon::http {

namespace {

void addRunReads(httplib::Server& srv, StationApi& st) {
    srv.Get("/api/runs", [&st](const httplib::Request&, httplib::Response& res) {
        auto runs = st.runs();
        if (!runs)
            return sendError(res, runs.error());
        nlohmann::json j = nlohmann::json::array();
        for (const auto& r : *runs)
            j.push_back(toJson(r));
        sendJson(res, j);
    });
    srv.Get(R"(/api/runs/([^/]+))", [&st](const httplib::Request& req, httplib::Response& res) {
        auto id = idParam(req, res);
        if (!id)
            return;
        auto r = st.run(*id);
        if (!r)
            return sendError(res, r.error());
        nlohmann::json j = toJson(*r);
        j["plan"] = r->plan;
        sendJson(res, j);
    });
    srv.Get(R"(/api/runs/([^/]+)/sections)",
            [&st](const httplib::Request& req, httplib::Response& res) {
                auto id = idParam(req, res);
                if (!id)
                    return;
                auto secs = st.sections(*id);
                if (!secs)
                    return sendError(res, secs.error());
                nlohmann::json j = nlohmann::json::array();
                for (const auto& s : *secs)
                    j.push_back(toJson(s));
                sendJson(res, j);
            });
    srv.Get(R"(/api/runs/([^/]+)/export)", [&st](const httplib::Request& req,
                                                 httplib::Response& res) {
        auto id = idParam(req, res);
        if (!id)
            return;
        const std::string format = req.has_param("format") ? req.get_param_value("format") : "json";
        auto out = st.exportRun(*id, format);
        if (!out)
            return sendError(res, out.error());
        res.set_content(*out, format == "csv" ? "text/csv" : "application/json");
    });
}

/// TOML unless the Content-Type says JSON, or says nothing and the body starts with '{'.
bool isJsonPlan(const httplib::Request& req) {
    const std::string type = req.get_header_value("Content-Type");
    if (type.find("json") != std::string::npos)
        return true;
    if (type.find("toml") != std::string::npos || req.body.empty())
        return false;
    const auto first = req.body.find_first_not_of(" \t\r\n");
    return req.body[first == std::string::npos ? 0 : first] == '{';
}

} // namespace

void addRunRoutes(httplib::Server& srv, StationApi& st, const Authoriser& authorised) {
    addRunReads(srv, st);
    srv.Post("/api/runs", [&st, authorised](const httplib::Request& req, httplib::Response& res) {
        if (!authorised(req, res))
            return;
        auto doc = parseDocument(
            req.body, isJsonPlan(req) ? DocumentFormat::Json : DocumentFormat::Toml, "plan");
        if (!doc)
            return sendError(res, doc.error());
        auto id = st.submitPlan(*doc, "plan");
        if (!id)
            return sendError(res, id.error());
        sendJson(res, {{"run_id", *id}}, 201);
    });
    auto control = [&srv, &st, authorised](const char* pattern, auto action) {
        srv.Post(pattern,
                 [&st, authorised, action](const httplib::Request& req, httplib::Response& res) {
                     auto rq = controlRequest(req, res, authorised);
                     if (!rq)
                         return;
                     core::Result<void> r = action(st, rq->id);
                     if (!r)
                         return sendError(res, r.error(), RequestKind::Control);
                     sendJson(res, {{"ok", true}});
                 });
    };
    control(R"(/api/runs/([^/]+)/pause)",
            [](StationApi& s, std::int64_t id) { return s.pauseRun(id); });
    srv.Post(R"(/api/runs/([^/]+)/resume)",
             [&st, authorised](const httplib::Request& req, httplib::Response& res) {
                 auto rq = controlRequest(
                     req, res, authorised, "reset_stage_alarm",
                     [](const nlohmann::json& v) { return v.is_boolean(); },
                     "body: expected {\"reset_stage_alarm\": true | false}");
                 if (!rq)
                     return;
                 auto r = st.resumeRun(rq->id, rq->body.value("reset_stage_alarm", false));
                 if (!r)
                     return sendError(res, r.error(), RequestKind::Control);
                 sendJson(res, {{"ok", true}});
             });
    control(R"(/api/runs/([^/]+)/cancel)",
            [](StationApi& s, std::int64_t id) { return s.cancelRun(id); });
}

} // namespace slicestation::daemon::http
