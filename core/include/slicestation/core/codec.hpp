// PNG and JPEG in memory, through libpng and libjpeg-turbo directly.
//
// Not through OpenCV's imgcodecs: loading that library pulls in GDAL, poppler, HDF5 and about
// 120 other shared libraries, which cost every slicectl process about 90 ms before main() ran
// (measured on the 2-core machine; docs/registration.md, "Speed"), and brought a hundred
// decoders nobody here reads into the daemon's address space.
#pragma once

#include "slicestation/core/result.hpp"

#include <opencv2/core.hpp>

#include <cstdint>
#include <span>
#include <string_view>
#include <vector>

namespace slicestation::core {

/// Decodes a PNG as stored, with no gamma or colour conversion: grey (1 channel, bit depths
/// under 8 expanded to 8), grey + alpha (2), RGB (3, BGR order), RGBA (4, BGRA order), palette
/// (3, BGR; a palette's transparency is dropped). 8-bit files give CV_8U, 16-bit files CV_16U.
/// Interlaced files are read. `what` names the data in messages (e.g. `PNG "a.png"`).
///
/// \return the image; IoError (not a PNG, corrupt or truncated: the message carries libpng's
///         reason), Unsupported (larger than kMaxImagePixels or kMaxImageBytes).
[[nodiscard]] Result<cv::Mat> decodePng(std::span<const std::uint8_t> data, std::string_view what);

/// How decodeJpeg returns the pixels.
enum class JpegPixels {
    AsStored, ///< grey JPEGs as 1 channel, colour ones as 3 (BGR)
    Grey,     ///< always 1 channel (the luma of a colour JPEG)
    Bgr,      ///< always 3 channels, BGR order
    Rgb,      ///< always 3 channels, RGB order
};

/// Decodes a baseline or progressive JPEG to 8-bit pixels. A warning of the decoder (a truncated
/// stream, corrupt entropy data) is an error here: a damaged capture is not stored as if whole.
/// Progressive files with more than 500 scans are refused (libjpeg-turbo's scan limit, against
/// streams built to take minutes).
///
/// \return the image; IoError (not a JPEG, corrupt or truncated), Unsupported (a CMYK or YCCK
///         JPEG, or larger than kMaxImagePixels or kMaxImageBytes).
[[nodiscard]] Result<cv::Mat> decodeJpeg(std::span<const std::uint8_t> data, JpegPixels pixels,
                                         std::string_view what);

/// Encodes CV_8U or CV_16U with 1, 3 (BGR) or 4 (BGRA) channels as PNG, tuned for speed as
/// OpenCV's encoder is by default (zlib level 1, run-length strategy, the Sub filter).
/// \return the file's bytes; InvalidArgument for any other type or an empty image.
[[nodiscard]] Result<std::vector<std::uint8_t>> encodePng(const cv::Mat& image);

/// Encodes CV_8U with 1 or 3 (BGR) channels as baseline JPEG at `quality` (1..100; colour with
/// 4:2:0 chroma subsampling). \return the bytes; InvalidArgument for any other type, an empty
/// image or a quality outside 1..100.
[[nodiscard]] Result<std::vector<std::uint8_t>> encodeJpeg(const cv::Mat& image, int quality);

} // namespace slicestation::core
