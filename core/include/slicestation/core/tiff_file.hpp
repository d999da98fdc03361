#pragma once
/// TIFF specifics beyond readImage/writeImage, over the same libtiff wrapper (image_file.cpp):
/// writing one page into a descriptor with extra tags (the daemon's OME-TIFF puts its OME-XML in
/// ImageDescription) and reading a file's ImageDescription back. libtiff diagnostics never reach
/// stderr; they are returned in Error::message.
///
/// Threading: re-entrant. Blocking: file I/O, no timeout.
#include "slicestation/core/result.hpp"

#include <opencv2/core/mat.hpp>

#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

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

/// How writeTiffPyramid lays a page out: square tiles, and reduced levels (each half the size of
/// the one before, rounded up) in the page's SubIFDs, as the OME-TIFF 6.0 specification of
/// sub-resolutions asks (Bio-Formats >= 6, QuPath, ABBA).
struct TiffPyramidLayout {
    int tileSizePx = 512; ///< tile width and height; a multiple of 16 in [16, 4096]
    /// Reduced levels are added while the last level's longer side exceeds this, so the
    /// smallest level fits in tileSizePx..maxTopSidePx (or is the full image when that fits).
    int maxTopSidePx = 1024;
    enum class BigTiff { Auto, Always, Never };
    /// Auto: BigTIFF when the uncompressed pixels of all levels pass bigTiffAboveBytes (a
    /// classic TIFF's offsets stop at 4 GiB; deflate may not shrink noise). Always: forced
    /// (readers that cannot take BigTIFF are rare: Bio-Formats, QuPath, libtiff, tifffile can).
    BigTiff bigTiff = BigTiff::Auto;
    std::uint64_t bigTiffAboveBytes = 3'500'000'000ull;
};

/// Sizes of the levels writeTiffPyramid writes for an image of `full` size: level 0 is `full`,
/// level k is ceil(full / 2^k), while the previous level's longer side exceeds maxTopSidePx.
std::vector<cv::Size> tiffPyramidLevels(cv::Size full, int maxTopSidePx);

/// Writes `image` (CV_8U or CV_16U, 1 or 3 channels, BGR stored as RGB) through `fd` (as
/// writeTiffPage) as one tiled, deflate-compressed page carrying `tags`, and its reduced levels
/// (cv::resize INTER_AREA of the full image, NewSubfileType 1) in that page's SubIFDs, largest
/// first. A reduced level carries the pixel size of its own pixels and no description.
/// \return InvalidArgument (a layout out of range), Unsupported (another type), IoError with
///         errno as writeTiffPage.
[[nodiscard]] Result<void> writeTiffPyramid(int fd, const std::filesystem::path& name,
                                            const cv::Mat& image, const TiffTags& tags,
                                            const TiffPyramidLayout& layout = {});

/// What a reader needs to serve tiles of a file writeTiffPyramid wrote.
struct TiffPyramidInfo {
    bool bigTiff = false;
    bool tiled = false;
    cv::Size tileSize;            ///< of level 0 (0 x 0 when stripped)
    std::vector<cv::Size> levels; ///< level 0 (first page), then its SubIFDs in file order
    std::vector<std::uint64_t> subIfdOffsets; ///< byte offsets of the SubIFDs (levels 1..)
    int cvType = -1;                          ///< OpenCV type of the first page's pixels
};

/// Reads the first page's layout and its SubIFDs' sizes (no pixels).
/// \return NotFound (no such file), IoError (not a readable TIFF, a SubIFD that cannot be read).
[[nodiscard]] Result<TiffPyramidInfo> readTiffPyramidInfo(const std::filesystem::path& path);

/// Decodes tile (tileX, tileY) of `level` (0: the first page, k: its k-th SubIFD) of a tiled
/// TIFF with 8/16-bit unsigned samples, 1 or 3 per pixel, interleaved. The tile is cut to the
/// level's edge (edge tiles are smaller); 3 samples come back as BGR.
/// \return NotFound (no such file, level or tile), Unsupported (not tiled, another pixel
///         layout, tiles over 4096 px), IoError (corrupt).
[[nodiscard]] Result<cv::Mat> readTiffTile(const std::filesystem::path& path, int level, int tileX,
                                           int tileY);

/// The ImageDescription of the first page, or nullopt when it has none.
/// \return NotFound (no such file), IoError (not a readable TIFF).
[[nodiscard]] Result<std::optional<std::string>>
readTiffDescription(const std::filesystem::path& path);

/// Makes every write of writeTiffPage (and so of writeImage's TIFF) fail with `err` (0: none),
/// so that tests reach the real error path without a full disk. Process-wide.
void setTiffWriteFaultForTesting(int err) noexcept;

} // namespace slicestation::core
