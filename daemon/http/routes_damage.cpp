// The lab's damage report and the station's flag score (docs/damage.md, "The score, the
// threshold and the lab's report").
#include "routes.hpp"

#include <cmath>
#include <cstdlib>

namespace slicestation::daemon::http {

void addDamageRoutes(httplib::Server& srv, StationApi& st, const Authoriser& authorised) {
    srv.Get("/api/damage/report", [&st](const httplib::Request& req, httplib::Response& res) {
        const std::string since = req.has_param("since") ? req.get_param_value("since") : "";
        double rate = 0.05;
        if (req.has_param("target_false_alarm_rate")) {
            const std::string v = req.get_param_value("target_false_alarm_rate");
            char* end = nullptr;
            rate = std::strtod(v.c_str(), &end);
            if (v.empty() || end != v.c_str() + v.size() || !std::isfinite(rate) || rate < 0 ||
                rate > 1)
                return sendError(res, 400,
                                 "target_false_alarm_rate: expected a number in [0, 1], got " +
                                     echo(v));
        }
        auto r = st.damageReport(since, rate);
        if (!r)
            return sendError(res, r.error());
        sendJson(res, *r);
    });
    srv.Get("/api/damage/threshold", [&st](const httplib::Request&, httplib::Response& res) {
        auto r = st.damageThreshold();
        if (!r)
            return sendError(res, r.error());
        sendJson(res, *r);
    });
    // POST, not PUT: the server admits GET, HEAD and POST only (a POST's body is bounded before
    // it is read). {"flag_score": x} sets it, {"flag_score": null} returns to the station file.
    srv.Post("/api/damage/threshold", [&st, authorised](const httplib::Request& req,
                                                        httplib::Response& res) {
        if (!authorised(req, res))
            return;
        const char* expected = "body: expected {\"flag_score\": a number in [0, 1] | null}";
        const auto body = nlohmann::json::parse(req.body, nullptr, false);
        if (body.is_discarded() || !body.is_object() || !body.contains("flag_score") ||
            !(body["flag_score"].is_number() || body["flag_score"].is_null()))
            return sendError(res, 400, expected);
        std::optional<double> score;
        if (body["flag_score"].is_number())
            score = body["flag_score"].get<double>();
        auto r = st.setDamageThreshold(score);
        if (!r)
            return sendError(res, r.error(), RequestKind::Control);
        sendJson(res, *r);
    });
}

} // namespace slicestation::daemon::http
