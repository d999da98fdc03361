#pragma once
/// `slicectl demo`: the station's main job on built-in defaults, with no hardware and no data
/// files: a section is generated from the built-in atlas with a known deformation, registered
/// exactly as `slicectl register` would, and checked against the truth.

#include "slicestation/core/result.hpp"

#include <nlohmann/json.hpp>

#include <cstdint>
#include <filesystem>

namespace slicestation::daemon {

struct DemoRequest {
    std::filesystem::path outputDir = "slicestation-demo";
    std::uint64_t seed = 7;
    bool damaged = false; ///< tear the generated section
};

/// Writes section.tif, atlas-labels.tif, landmarks.csv, result.json, overlay.png and
/// truth.csv into outputDir and returns a summary with the landmark errors (atlas px).
[[nodiscard]] core::Result<nlohmann::json> runDemo(const DemoRequest& request);

} // namespace slicestation::daemon
