// Cells per region (docs/cells.md): a section's COUNTS.csv and a run's summed counts, as CSV.
#include "routes.hpp"

namespace slicestation::daemon::http {

void addCountRoutes(httplib::Server& srv, StationApi& st) {
    srv.Get(R"(/api/sections/([^/]+)/counts)",
            [&st](const httplib::Request& req, httplib::Response& res) {
                auto id = idParam(req, res);
                if (!id)
                    return;
                auto csv = st.sectionCounts(*id);
                if (!csv)
                    return sendError(res, csv.error());
                res.set_content(*csv, "text/csv; charset=utf-8");
            });
    srv.Get(R"(/api/runs/([^/]+)/counts)",
            [&st](const httplib::Request& req, httplib::Response& res) {
                auto id = idParam(req, res);
                if (!id)
                    return;
                auto csv = st.runCounts(*id);
                if (!csv)
                    return sendError(res, csv.error());
                res.set_content(*csv, "text/csv; charset=utf-8");
            });
}

} // namespace slicestation::daemon::http
