#pragma once
/// `slicectl register`: register one section image to one atlas label slice and write the result.

#include "slicestation/core/result.hpp"

#include <nlohmann/json.hpp>

#include <filesystem>
#include <optional>

namespace slicestation::daemon {

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
/// \return the first error met: NotFound / IoError for files, InvalidArgument for malformed input
///         (the message names the file and what is wrong), NoTissue. Nothing is written then.
[[nodiscard]] core::Result<nlohmann::json> runRegister(const RegisterRequest& request);

/// Writes text to `path` through a temporary file, fsync and rename.
[[nodiscard]] core::Result<void> writeFileAtomically(const std::filesystem::path& path,
                                                     const std::string& text);

} // namespace slicestation::daemon
