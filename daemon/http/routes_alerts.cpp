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
        auto rq = controlRequest(
            req, res, authorised, "action", [](const nlohmann::json& v) { return v.is_string(); },
            "body: expected {\"action\": \"rescan\" | \"accept\" | text}");
        if (!rq)
            return;
        auto a = st.acknowledgeAlert(rq->id, rq->body.value("action", std::string("accept")));
        if (!a)
            return sendError(res, a.error(), RequestKind::Control);
        sendJson(res, toJson(*a));
    });
}

} // namespace slicestation::daemon::http
