#pragma once
/// Reading and writing section images (PNG, TIFF) as stored, without conversion.
///
/// Threading: both functions are re-entrant; they may run concurrently on different files.
/// libtiff diagnostics never reach stderr: they are captured and returned in Error::message.
/// Blocking: both block on file I/O; no timeout.

#include "slicestation/core/result.hpp"

#include <opencv2/core/mat.hpp>

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <optional>

namespace slicestation::core {

/// Largest image readImage accepts, checked from the file's header before anything is decoded:
/// 2^30 pixels (e.g. 32768 x 32768, a 21 x 21 mm tiled section at 0.65 um/px) and 4 GiB once
/// decoded (pixels x channels kept x bytes per sample; every page of an ImageJ hyperstack
/// counted). A file may be tiny and claim gigapixels; those limits keep one image from taking
/// the station's memory.
inline constexpr std::uint64_t kMaxImagePixels = std::uint64_t{1} << 30;
inline constexpr std::uint64_t kMaxImageBytes = std::uint64_t{4} << 30;

/// Reads TIFF, PNG or JPEG (chosen by content, not extension) as stored; no other format is
/// read (decoders of other formats allocate whatever a few header bytes claim).
///
/// Depths: CV_8U, CV_16U, CV_32S (from int32 and uint32 samples; a uint32 value above INT32_MAX
/// is Unsupported), CV_32F. Channels 1..4. Colour images (TIFF photometric RGB/YCbCr, PNG) come
/// in OpenCV's BGR(A) order; other multi-sample TIFFs keep their sample order.
/// TIFF is read with libtiff: strips or tiles, contiguous or separate planes, either byte order,
/// any codec libtiff was built with. A TIFF with more than 4 samples per pixel yields its first 4
/// samples (documented choice: extra fluorescence channels are dropped, not an error).
/// Multi-page TIFF: the first page only, except ImageJ hyperstacks (ImageDescription starting
/// "ImageJ=" with "channels=C", one sample per page), whose first min(C, 4) pages are the channels
/// of the first slice and become the image's channels in page order (the ABBA sections are such
/// files). PNG and JPEG are decoded as stored by libpng and libjpeg-turbo (codec.hpp: decodePng,
/// decodeJpeg with JpegPixels::AsStored) once their headers are checked; arithmetic-coded JPEG
/// is Unsupported.
///
/// Size: at most kMaxImagePixels and kMaxImageBytes, from the TIFF tags or the PNG or JPEG
/// header, and the file must be able to hold what its header claims. Float images must be finite.
///
/// \return the image (never empty); NotFound (no such file), IoError (unreadable, empty, corrupt
///         or truncated file, or not a TIFF, PNG or JPEG), Unsupported (bit depth, sample format,
///         palette/bilevel TIFF, or an
///         image beyond the size limits: the message gives its size and the limit), InvalidArgument
///         (a float image holding NaN or infinity: the message names the file and the first such
///         pixel).
[[nodiscard]] Result<cv::Mat> readImage(const std::filesystem::path& path);

/// Width and height from the frame header (the first SOFn marker) of the JPEG in `data`, e.g. a
/// camera's MJPEG frame, read before it is decoded; nullopt when `data` is no JPEG with a frame
/// header. Decoders allocate from this header alone, so a frame is checked against the size the
/// camera negotiated first.
[[nodiscard]] std::optional<cv::Size> jpegFrameSize(const std::uint8_t* data, std::size_t size);

/// Writes `image` in the format chosen by the extension (case-insensitive):
/// - .png: CV_8U or CV_16U, 1, 3 or 4 channels (BGR(A) order), via libpng (codec.hpp, encodePng);
/// - .tif/.tiff: via libtiff, deflate-compressed, CV_8U, CV_16U, CV_32S (written as uint32 label
///   image, so values must be >= 0), CV_32F; 1..4 channels (3 and 4 are BGR(A), stored as RGB(A)).
/// The data goes to a temporary file in the same directory, is fsync'ed, then renamed over
/// `path`: a reader sees either the old file or the complete new one, never a partial file.
///
/// \return InvalidArgument (empty image, negative CV_32S value), Unsupported (extension, depth or
///         channel count), NotFound (directory missing), IoError (write, fsync or rename failed).
[[nodiscard]] Result<void> writeImage(const std::filesystem::path& path, const cv::Mat& image);

} // namespace slicestation::core
