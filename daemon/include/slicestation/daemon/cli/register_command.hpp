#pragma once
/// `slicectl register`: register one section image to one atlas label slice and write the result
/// (the registration service, station/registration_service.hpp, with slicectl's points CSV).
#include "slicestation/core/result.hpp"
#include "slicestation/daemon/station/registration_service.hpp"

#include <nlohmann/json.hpp>

namespace slicestation::daemon {

/// registerSectionFiles with the `--points` CSV read by readPointsCsv. \return the JSON that
/// was written to `output`; the errors of registerSectionFiles and readPointsCsv.
[[nodiscard]] core::Result<nlohmann::json> runRegister(const RegisterRequest& request);

} // namespace slicestation::daemon
