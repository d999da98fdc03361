// Alerts: the list (all, or ?open=1) and acknowledging one.
#include "routes.hpp"

namespace slicestation::daemon::http {

void addAlertRoutes(httplib::Server& srv, StationApi& st, const Authoriser& authorised) {
    srv.Get("/api/alerts", [&st](const httplib::Request& req, httplib::Response& res) {
        const bool open = req.has_param("open") && req.get_param_value("open") != "0";
        auto a = st.alerts(open);
        if (!a)
            return sendError(res, a.error());
        nlohmann::json j = nlohmann::json::array();
        for (const auto& x : *a)
            j.push_back(toJson(x));
        sendJson(res, j);
    });
    srv.Post(R"(/api/alerts/([^/]+)/ack)", [&st, authorised](const httplib::Request& req,
                                                             httplib::Response& res) {
        if (!authorised(req, res))
            return;
        auto id = idParam(req, res);
        if (!id)
            return;
        std::string action = "accept";
        if (!req.body.empty()) {
            auto j = nlohmann::json::parse(req.body, nullptr, false);
            if (j.is_discarded() || !j.is_object() ||
                (j.contains("action") && !j["action"].is_string()))
                return sendError(res, 400,
                                 "body: expected {\"action\": \"rescan\" | \"accept\" | text}");
            action = j.value("action", action);
        }
        auto a = st.acknowledgeAlert(*id, action);
        if (!a)
            return sendError(res, a.error(), RequestKind::Control);
        sendJson(res, toJson(*a));
    });
}

} // namespace slicestation::daemon::http
