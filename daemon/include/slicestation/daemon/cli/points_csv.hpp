#pragma once
/// The `--points` CSV of `slicectl register`: header `x,y`, one point a row, section-image pixel
/// coordinates (origin top-left, x right, y down, pixel centres at integers).

#include "slicestation/core/result.hpp"

#include <opencv2/core.hpp>

#include <filesystem>
#include <string_view>
#include <vector>

namespace slicestation::daemon {

/// Parses CSV text with core::parseCsv (RFC 4180: quoted fields, CRLF, a byte-order mark, blank
/// lines), then allows spaces around fields and extra columns after x,y (ignored).
/// \return InvalidArgument naming the line and the problem: broken quoting, missing or wrong
/// header, wrong field count, non-numeric or non-finite value.
[[nodiscard]] core::Result<std::vector<cv::Point2d>> parsePointsCsv(std::string_view text);

/// Reads and parses a file. \return NotFound, IoError, or the errors of parsePointsCsv.
[[nodiscard]] core::Result<std::vector<cv::Point2d>>
readPointsCsv(const std::filesystem::path& path);

} // namespace slicestation::daemon
