#pragma once
/// `slicectl register`: register one section image to one atlas label slice and write the result.

#include "slicestation/core/result.hpp"

#include <nlohmann/json.hpp>

#include <filesystem>
#include <optional>

namespace slicestation::daemon {

/// Pixel sizes a request may give (micrometres per pixel): from a 100x objective to a
/// 1 mm-per-pixel thumbnail.
inline constexpr double kMinUmPerPx = 0.01;
inline constexpr double kMaxUmPerPx = 1000;
/// Section images registered: 300 to 8000 px on each side (README). Smaller holds too little
/// tissue to find edges in; larger is a tiled scan to be reduced before registration.
inline constexpr int kMinSectionSidePx = 300;
inline constexpr int kMaxSectionSidePx = 8000;

struct RegisterRequest {
    std::filesystem::path atlas;  ///< label image (8/16/32-bit ids or colour-coded RGB)
    std::filesystem::path image;  ///< section image (PNG or TIFF)
    std::optional<std::filesystem::path> points;       ///< CSV x,y to map
    std::filesystem::path output;                      ///< RESULT.json
    std::optional<std::filesystem::path> overlay;      ///< PNG
    std::optional<std::filesystem::path> warpedLabels; ///< TIFF, CV_32S ids at section size
    double imageUmPerPx = 0; ///< 0 = unknown
    double atlasUmPerPx = 0; ///< 0 = unknown
    int workingMaxSide = 1024;
};

/// Reads the inputs, registers, writes every requested output (each atomically: a reader never
/// sees half a file), and returns the JSON that was written to `output`.
/// Checks: pixel sizes 0 (unknown) or finite within [kMinUmPerPx, kMaxUmPerPx]; the section
/// kMinSectionSidePx..kMaxSectionSidePx on each side; the atlas labels holding both brain
/// (non-zero ids) and outside (0).
/// \return the first error met: NotFound / IoError for files, InvalidArgument for malformed input
///         (the message names the file and what is wrong), NoTissue. Nothing is written then.
[[nodiscard]] core::Result<nlohmann::json> runRegister(const RegisterRequest& request);

/// Writes text to `path` through a temporary file, fsync and rename.
[[nodiscard]] core::Result<void> writeFileAtomically(const std::filesystem::path& path,
                                                     const std::string& text);

} // namespace slicestation::daemon
