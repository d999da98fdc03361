// The page, the station's status and the live view.
#include "routes.hpp"

#include "slicestation/daemon/http/web_page.hpp"
#include "slicestation/pipeline/frame_image.hpp"

namespace slicestation::daemon::http {

void addPageRoutes(httplib::Server& srv, StationApi& st) {
    // The page: self-contained, and the browser is told to load nothing from elsewhere.
    srv.Get("/", [](const httplib::Request&, httplib::Response& res) {
        res.set_header("Content-Security-Policy",
                       "default-src 'self'; img-src 'self' blob:; style-src 'unsafe-inline'; "
                       "script-src 'unsafe-inline'; connect-src 'self'");
        res.set_header("X-Content-Type-Options", "nosniff");
        res.set_header("Cache-Control", "no-cache");
        const auto page = webPage();
        res.set_content(page.data(), page.size(), "text/html; charset=utf-8");
    });
    // The station's status with "stage": the station's last known position (read during moves
    // on stages that report it), else where the stage was at the latest camera frame; absent
    // when neither is known.
    srv.Get("/api/status", [&st](const httplib::Request&, httplib::Response& res) {
        nlohmann::json j = st.status();
        if (auto frame = st.liveFrame(); !j.contains("stage") && frame && frame->metadata.stage) {
            const auto& p = *frame->metadata.stage;
            j["stage"] = {{"x_um", p.xUm}, {"y_um", p.yUm}, {"z_um", p.zUm}};
        }
        sendJson(res, j);
    });
    // The latest camera frame, scaled to ?width= (16..4096).
    srv.Get("/api/live.jpg", [&st](const httplib::Request& req, httplib::Response& res) {
        auto width = intQuery(req, res, "width", 16, 4096, 1024);
        if (!width)
            return;
        auto frame = st.liveFrame();
        if (!frame)
            return sendError(res, 404, "no frame yet");
        sendImage(res, pipeline::frameToMat(*frame), *width, ".jpg");
    });
}

} // namespace slicestation::daemon::http
