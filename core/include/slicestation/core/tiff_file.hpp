#pragma once
/// TIFF specifics beyond readImage/writeImage, over the same libtiff wrapper (image_file.cpp):
/// writing one page into a descriptor with extra tags (the daemon's OME-TIFF puts its OME-XML in
/// ImageDescription) and reading a file's ImageDescription back. libtiff diagnostics never reach
/// stderr; they are returned in Error::message.
///
/// Threading: re-entrant. Blocking: file I/O, no timeout.
#include "slicestation/core/result.hpp"

#include <opencv2/core/mat.hpp>

#include <filesystem>
#include <optional>
#include <string>

namespace slicestation::core {

/// Tags a page may carry beside the pixels. Empty strings and a pixel size of 0 are not written.
struct TiffTags {
    std::string imageDescription; ///< e.g. OME-XML (must not hold a NUL byte)
    std::string software;
    double umPerPx = 0; ///< written as XResolution/YResolution in pixels per centimetre
};

/// Writes `image` as one deflate-compressed TIFF page (strips of about 64 KiB) through `fd`,
/// which must be empty, open for reading and writing, and stays the caller's. Depths and channels
/// as writeImage's TIFF: CV_8U, CV_16U, CV_32S (as uint32), CV_32F; 1..4 channels, BGR(A) stored
/// as RGB(A). `name` is used in messages only.
/// \return IoError carrying the errno of the first failed system call (ENOSPC on a full disk,
///         EIO when libtiff failed without one); Internal when libtiff refuses the tags.
[[nodiscard]] Result<void> writeTiffPage(int fd, const std::filesystem::path& name,
                                         const cv::Mat& image, const TiffTags& tags = {});

/// The ImageDescription of the first page, or nullopt when it has none.
/// \return NotFound (no such file), IoError (not a readable TIFF).
[[nodiscard]] Result<std::optional<std::string>>
readTiffDescription(const std::filesystem::path& path);

/// Makes every write of writeTiffPage (and so of writeImage's TIFF) fail with `err` (0: none),
/// so that tests reach the real error path without a full disk. Process-wide.
void setTiffWriteFaultForTesting(int err) noexcept;

} // namespace slicestation::core
