#include "slicestation/daemon/storage/ome_tiff.hpp"

#include "ome_text.hpp"

#include "slicestation/core/atomic_file.hpp"

#include "slicestation/core/image_file.hpp"
#include "slicestation/core/tiff_file.hpp"
#include "slicestation/daemon/version.hpp"

#include <opencv2/core.hpp>

#include <algorithm>
#include <array>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <ctime>
#include <optional>
#include <regex>
#include <vector>
namespace slicestation::daemon {
namespace {

namespace fs = std::filesystem;
using core::ErrorCode;
using core::makeError;
using ome_text::formatDouble;
using ome_text::quoted;

bool hasControlCharacters(std::string_view text) {
    return std::any_of(text.begin(), text.end(),
                       [](char c) { return static_cast<unsigned char>(c) < 0x20; });
}

bool isIso8601(const std::string& text) {
    static const std::regex pattern(
        R"(\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}(\.\d{1,9})?(Z|[+-]\d{2}:\d{2})?)");
    return std::regex_match(text, pattern);
}

std::string utcNowIso8601() {
    const std::time_t now = std::time(nullptr);
    std::tm tm{};
    gmtime_r(&now, &tm);
    std::array<char, 32> buf{};
    std::strftime(buf.data(), buf.size(), "%Y-%m-%dT%H:%M:%SZ", &tm);
    return buf.data();
}

core::Result<void> validate(const fs::path& path, const cv::Mat& image, const OmeTiffInfo& info) {
    const std::string what = "cannot write OME-TIFF " + quoted(path) + ": ";
    if (image.empty())
        return makeError(ErrorCode::InvalidArgument, what + "empty image");
    const int t = image.type();
    if (t != CV_8UC1 && t != CV_16UC1 && t != CV_8UC3) {
        return makeError(ErrorCode::InvalidArgument,
                         what + "image type " + cv::typeToString(t) +
                             " (supported: CV_8UC1, CV_16UC1, CV_8UC3)");
    }
    if (!(info.umPerPx > 0) || !std::isfinite(info.umPerPx)) {
        return makeError(ErrorCode::InvalidArgument, what + "pixel size umPerPx must be > 0, not " +
                                                         formatDouble(info.umPerPx));
    }
    if (!std::isfinite(info.stage.xUm) || !std::isfinite(info.stage.yUm) ||
        !std::isfinite(info.stage.zUm)) {
        return makeError(ErrorCode::InvalidArgument, what + "stage position is not finite");
    }
    if (info.exposureUs < 0) {
        return makeError(ErrorCode::InvalidArgument, what + "exposureUs is negative");
    }
    if (!(info.gain > 0) || !std::isfinite(info.gain)) {
        return makeError(ErrorCode::InvalidArgument, what + "gain must be > 0");
    }
    if (!info.acquiredUtc.empty() && !isIso8601(info.acquiredUtc)) {
        return makeError(ErrorCode::InvalidArgument,
                         what + "acquiredUtc '" + info.acquiredUtc +
                             "' is not an ISO 8601 date-time (YYYY-MM-DDThh:mm:ss[.f][Z|+hh:mm])");
    }
    if (hasControlCharacters(info.name) || hasControlCharacters(info.channel) ||
        hasControlCharacters(info.objective)) {
        return makeError(ErrorCode::InvalidArgument,
                         what + "name, channel and objective must not hold control characters");
    }
    return {};
}

core::Result<void> writeAtomic(const fs::path& path, const cv::Mat& image, OmeTiffInfo info,
                               const OmeTiffLayout& layout) {
    if (auto valid = validate(path, image, info); !valid)
        return valid;
    if (info.acquiredUtc.empty())
        info.acquiredUtc = utcNowIso8601();
    const std::string xml = makeOmeXml(image.cols, image.rows, image.type(), info);

    // Never over an existing file: it may be an image the journal refers to (EEXIST instead).
    const core::TiffTags tags{xml, std::string("slicestation ") + kVersion, info.umPerPx};
    auto r = core::replaceAtomically(
        path,
        [&](int fd, const fs::path& tmp) {
            return core::writeTiffPyramid(fd, tmp, image, tags, layout);
        },
        core::Replace::Never);
    // This writer's contract: a missing directory is an IoError (with ENOENT) like any other.
    if (!r && r.error().code == ErrorCode::NotFound)
        return makeError(ErrorCode::IoError, r.error().message, r.error().sysErrno);
    return r;
}

core::Result<std::string> readDescription(const fs::path& path) {
    auto description = core::readTiffDescription(path);
    if (!description)
        return description.error();
    if (!*description)
        return makeError(ErrorCode::IoError,
                         "TIFF " + quoted(path) + " has no ImageDescription (not an OME-TIFF)");
    return std::move(**description);
}

core::Result<OmeTiffImage> readImpl(const fs::path& path) {
    std::error_code ec;
    if (!fs::exists(path, ec)) {
        return makeError(ErrorCode::NotFound, "OME-TIFF " + quoted(path) + " does not exist");
    }
    auto description = readDescription(path);
    if (!description)
        return description.error();
    auto pixels = core::readImage(path);
    if (!pixels) {
        core::Error e = pixels.error();
        if (e.code == ErrorCode::NotFound)
            e.code = ErrorCode::IoError;
        return e;
    }
    const int t = pixels->type();
    if (t != CV_8UC1 && t != CV_16UC1 && t != CV_8UC3) {
        return makeError(ErrorCode::Unsupported,
                         "OME-TIFF " + quoted(path) + ": pixel type " + cv::typeToString(t) +
                             " (supported: 8-bit and 16-bit mono, 8-bit RGB)");
    }
    auto content = parseOmeXml(*description);
    if (!content) {
        return makeError(ErrorCode::IoError,
                         "OME-TIFF " + quoted(path) + ": " + content.error().message);
    }
    if (content->sizeX != pixels->cols || content->sizeY != pixels->rows) {
        return makeError(ErrorCode::IoError,
                         "OME-TIFF " + quoted(path) + ": OME-XML says " +
                             std::to_string(content->sizeX) + " x " +
                             std::to_string(content->sizeY) + " px, the TIFF holds " +
                             std::to_string(pixels->cols) + " x " + std::to_string(pixels->rows));
    }
    return OmeTiffImage{std::move(pixels.value()), std::move(content->info)};
}

} // namespace

core::Result<OmeTiffImage> readOmeTiff(const std::filesystem::path& path) {
    try {
        return readImpl(path);
    } catch (const std::exception& e) {
        return makeError(ErrorCode::Internal,
                         "cannot read OME-TIFF " + quoted(path) + ": " + e.what());
    }
}

void setOmeTiffWriteFaultForTesting(int err) noexcept {
    core::setTiffWriteFaultForTesting(err);
}

core::Result<void> writeOmeTiffAtomic(const std::filesystem::path& path, const cv::Mat& image,
                                      const OmeTiffInfo& info, const OmeTiffLayout& layout) {
    try {
        return writeAtomic(path, image, info, layout);
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::Internal,
                         "cannot write OME-TIFF " + quoted(path) + ": OpenCV: " + e.what());
    } catch (const std::exception& e) {
        return makeError(ErrorCode::Internal,
                         "cannot write OME-TIFF " + quoted(path) + ": " + e.what());
    }
}

} // namespace slicestation::daemon
