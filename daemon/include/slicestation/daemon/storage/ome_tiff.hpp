#pragma once
/// Section images as single-plane OME-TIFF files (OME-XML schema 2016-06), readable by Fiji,
/// QuPath and anything else built on Bio-Formats.
///
/// Layout written (docs/images.md): the full-resolution image in the first IFD, deflate-compressed
/// 512 x 512 tiles with the horizontal predictor (lossless); reduced levels (factor 2, cv::resize
/// INTER_AREA of the full image) in that IFD's SubIFDs, largest first, until a level fits in
/// 1024 px, as the OME-TIFF specification of sub-resolutions (Bio-Formats >= 6) asks; classic
/// little-endian TIFF, BigTIFF when the pixels of all levels pass ~3.5 GB (or when forced). The
/// OME-XML sits in the first IFD's ImageDescription and states:
/// - `Pixels@PhysicalSizeX/Y` with unit "µm" (also written as TIFF X/YResolution in pixels per
///   centimetre for readers that ignore OME-XML; each reduced level carries its own);
/// - one `Plane` with `PositionX/Y/Z` (unit "µm"): the stage position of the image CENTRE (the
///   point on the optical axis for one field; the planned section centre for a stitched image),
///   repeated as a `StageLabel` named "image centre"; and `ExposureTime` (unit "µs");
/// - the channel name and colour (`Color`, a signed 32-bit RGBA integer); an RGB image is one
///   channel with SamplesPerPixel="3" (SizeC="3"), interleaved, as Bio-Formats writes RGB;
/// - `Image@Name`, `AcquisitionDate`, the objective (`Instrument/Objective@Model`, with
///   `NominalMagnification` when its name reads like "4x", referenced by `ObjectiveSettings`),
///   the gain as the channel's `DetectorSettings@Gain` (with the Instrument/Detector the schema
///   requires for it), and the software and its version in `OME@Creator` and the TIFF Software tag.
///
/// Threading: re-entrant; different files may be written and read concurrently.
/// Blocking: file I/O and fsync, no timeout. libtiff diagnostics never reach stderr: they are
/// returned in Error::message.

#include "slicestation/core/result.hpp"
#include "slicestation/core/stage.hpp"
#include "slicestation/core/tiff_file.hpp"

#include <opencv2/core/mat.hpp>

#include <cstdint>
#include <filesystem>
#include <string>
#include <string_view>

namespace slicestation::daemon {

struct OmeTiffInfo {
    double umPerPx = 0;      ///< pixel size at the sample, µm (square pixels); must be > 0
    hw::StagePosition stage; ///< stage position of the image centre, µm
    std::string channel = "fluorescence";
    std::string name;            ///< image name (e.g. "slide3-section05"); may be empty
    std::int64_t exposureUs = 0; ///< >= 0
    double gain = 1;             ///< analogue gain, > 0
    /// ISO 8601 date-time, e.g. "2024-05-01T22:13:05Z" or with fraction/offset. Empty: the UTC
    /// time of writing is stored (and read back).
    std::string acquiredUtc;
    std::string objective; ///< the station file's objective name (e.g. "4x"); may be empty
    /// Display colour of the channel, 0xRRGGBBAA (OME's Channel@Color); white by default.
    std::uint32_t channelRgba = 0xFFFFFFFFu;
};

/// How the file is laid out (tiles, pyramid, BigTIFF); the defaults are what the station writes.
using OmeTiffLayout = core::TiffPyramidLayout;

/// Writes `image` (CV_8UC1, CV_16UC1 or CV_8UC3 in OpenCV's BGR order; stored as RGB) to `path`
/// atomically through core::replaceAtomically (core/atomic_file.hpp: a temporary file beside
/// it, fsync'ed, renamed, the directory fsync'ed), never over an existing file (RENAME_NOREPLACE,
/// or link + unlink where the file system lacks it). A reader never sees a partial file; on
/// failure the temporary file is removed and `path` is untouched. An existing `path` is never
/// replaced (IoError with sysErrno EEXIST): whether an old file may go is the caller's decision.
///
/// \return InvalidArgument (empty image, unsupported Mat type, umPerPx not > 0, non-finite
///         stage position, negative exposure, gain not > 0, acquiredUtc not ISO 8601, a name or
///         channel with control characters, a layout out of range), IoError naming the path with
///         Error::sysErrno set (missing or read-only directory, disk full = ENOSPC, `path` exists =
///         EEXIST, fsync or rename failure).
[[nodiscard]] core::Result<void> writeOmeTiffAtomic(const std::filesystem::path& path,
                                                    const cv::Mat& image, const OmeTiffInfo& info,
                                                    const OmeTiffLayout& layout = {});

/// For tests of storage faults only: from now on every write(2) of writeOmeTiffAtomic fails
/// with `err` (e.g. ENOSPC) through the writer's real error path, until called with 0.
/// Process-wide.
void setOmeTiffWriteFaultForTesting(int err) noexcept;

struct OmeTiffImage {
    cv::Mat image; ///< CV_8UC1, CV_16UC1 or CV_8UC3 (BGR)
    OmeTiffInfo info;
};

/// Reads an OME-TIFF written by writeOmeTiffAtomic (or another OME-TIFF writer: units of length
/// and time are converted, e.g. nm or mm to µm, s or ms to µs). Pixels of the first IFD (the
/// full resolution; reduced levels are read with core::readTiffTile).
/// Fields absent from the OME-XML keep OmeTiffInfo's defaults, except PhysicalSizeX, which is
/// required (a missing pixel size is an error, never assumed 1).
///
/// \return NotFound (no such file), Unsupported (a pixel type other than the three written),
///         IoError (not a TIFF, corrupt, no or malformed OME-XML, no PhysicalSizeX,
///         SizeX/SizeY differing from the TIFF).
[[nodiscard]] core::Result<OmeTiffImage> readOmeTiff(const std::filesystem::path& path);

/// The OME-XML document writeOmeTiffAtomic stores for an image of `size` and `cvType`.
/// Exposed for tests and for tools that want to show it. Does not validate `info`.
std::string makeOmeXml(int width, int height, int cvType, const OmeTiffInfo& info);

/// Parses an OME-XML document into OmeTiffInfo (plus SizeX/SizeY of the first Image).
struct OmeXmlContent {
    OmeTiffInfo info;
    int sizeX = 0;
    int sizeY = 0;
};
/// \return IoError (malformed XML, no OME/Image/Pixels element, PhysicalSizeX missing, not > 0,
///         or in an unknown unit, a number that does not parse).
[[nodiscard]] core::Result<OmeXmlContent> parseOmeXml(std::string_view xml);

} // namespace slicestation::daemon
