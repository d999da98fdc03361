// Sections: the detail, the latest image and overlay, the atlas region at a pixel, a rescan.
#include "routes.hpp"

#include "slicestation/core/codec.hpp"

#include <string>
#include <vector>

namespace slicestation::daemon::http {

void addSectionRoutes(httplib::Server& srv, StationApi& st, const Authoriser& authorised) {
    srv.Get(R"(/api/sections/([^/]+))", [&st](const httplib::Request& req, httplib::Response& res) {
        auto id = idParam(req, res);
        if (!id)
            return;
        auto d = st.sectionDetail(*id);
        if (!d)
            return sendError(res, d.error());
        sendJson(res, *d);
    });
    // A section's latest image, or its overlay once registered, scaled to ?width= (16..4096).
    auto imageRoute = [&srv, &st](const char* pattern, bool overlay) {
        srv.Get(pattern, [&st, overlay](const httplib::Request& req, httplib::Response& res) {
            auto id = idParam(req, res);
            if (!id)
                return;
            auto width = intQuery(req, res, "width", 16, 4096, 1024);
            if (!width)
                return;
            auto image = st.sectionImage(*id, overlay);
            if (!image)
                return sendError(res, image.error());
            sendImage(res, *image, *width, overlay ? ".png" : ".jpg");
        });
    };
    imageRoute(R"(/api/sections/([^/]+)/image\.jpg)", false);
    imageRoute(R"(/api/sections/([^/]+)/overlay\.png)", true);
    // The tile pyramid of the section's latest image (docs/images.md) and one tile as PNG. The
    // numbers are bounded by the pattern (a longer one finds no route: 404); the station
    // answers 404 for a level or tile the image does not have.
    srv.Get(R"(/api/sections/([^/]+)/pyramid)",
            [&st](const httplib::Request& req, httplib::Response& res) {
                auto id = idParam(req, res);
                if (!id)
                    return;
                auto p = st.sectionPyramid(*id);
                if (!p)
                    return sendError(res, p.error());
                nlohmann::json levels = nlohmann::json::array();
                for (const auto& l : p->levels)
                    levels.push_back({l.width, l.height});
                sendJson(res, {{"tile_px", p->tileSizePx}, {"levels", levels}});
            });
    srv.Get(R"(/api/sections/([^/]+)/tiles/([0-9]{1,2})/([0-9]{1,6})_([0-9]{1,6})\.png)",
            [&st](const httplib::Request& req, httplib::Response& res) {
                auto id = idParam(req, res);
                if (!id)
                    return;
                const auto number = [&](std::size_t k) { return std::stoi(req.matches[k].str()); };
                auto tile = st.sectionTile(*id, number(2), number(3), number(4));
                if (!tile)
                    return sendError(res, tile.error());
                auto png = core::encodePng(*tile);
                if (!png)
                    return sendError(res, 500, "cannot encode the tile: " + png.error().message);
                res.set_header("Cache-Control", "private, max-age=60");
                res.set_content(std::string(png->begin(), png->end()), "image/png");
            });
    // The atlas region at a pixel of the section's latest capture (full resolution), or with
    // ?of_width=W at a pixel of the image shown scaled to width W (the page's overlay).
    srv.Get(R"(/api/sections/([^/]+)/region)",
            [&st](const httplib::Request& req, httplib::Response& res) {
                auto id = idParam(req, res);
                if (!id)
                    return;
                auto x = intQuery(req, res, "x", 0, 1 << 20, std::nullopt);
                if (!x)
                    return;
                auto y = intQuery(req, res, "y", 0, 1 << 20, std::nullopt);
                if (!y)
                    return;
                auto ofWidth = intQuery(req, res, "of_width", 1, 1 << 20, 0);
                if (!ofWidth)
                    return;
                auto r = st.regionAt(*id, *x, *y, *ofWidth);
                if (!r)
                    return sendError(res, r.error());
                nlohmann::json j{{"id", r->id}, {"x", r->x}, {"y", r->y}};
                if (!r->name.empty()) {
                    j["name"] = r->name;
                    j["acronym"] = r->acronym;
                }
                sendJson(res, j);
            });
    srv.Post(R"(/api/sections/([^/]+)/rescan)",
             [&st, authorised](const httplib::Request& req, httplib::Response& res) {
                 if (!authorised(req, res))
                     return;
                 auto id = idParam(req, res);
                 if (!id)
                     return;
                 auto r = st.requestRescan(*id);
                 if (!r)
                     return sendError(res, r.error(), RequestKind::Control);
                 sendJson(res, {{"ok", true}});
             });
}

} // namespace slicestation::daemon::http
