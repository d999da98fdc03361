#include "slicestation/daemon/cli/register_command.hpp"

#include "slicestation/daemon/cli/points_csv.hpp"

namespace slicestation::daemon {

core::Result<nlohmann::json> runRegister(const RegisterRequest& rq) {
    auto r =
        registerSectionFiles(rq, [](const std::filesystem::path& p) { return readPointsCsv(p); });
    if (!r)
        return r.error();
    return std::move(r->document);
}

} // namespace slicestation::daemon
