#include "slicestation/daemon/storage/ome_tiff.hpp"

#include "ome_text.hpp"

#include "slicestation/core/atomic_file.hpp"

#include "slicestation/core/image_file.hpp"
#include "slicestation/core/unique_fd.hpp"

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <tiffio.h>

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <bit>
#include <cerrno>
#include <charconv>
#include <chrono>
#include <cmath>
#include <cstdarg>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <memory>
#include <optional>
#include <random>
#include <regex>
#include <vector>
namespace slicestation::daemon {
namespace {

namespace fs = std::filesystem;
using core::ErrorCode;
using core::makeError;
using ome_text::formatDouble;
using ome_text::quoted;

std::string errnoText(int err) {
    return std::string(std::strerror(err)) + " (errno " + std::to_string(err) + ")";
}

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

// ---------------------------------------------------------------------------------------------
// libtiff over a file descriptor we own, so that the errno of a failing write (ENOSPC) is kept.

/// errno every write fails with, for tests (0: none); see setOmeTiffWriteFaultForTesting.
std::atomic<int> gWriteFault{0};

struct TiffIo {
    int fd = -1;
    int firstErrno = 0; ///< errno of the first failed system call
    std::string errors; ///< libtiff's error messages
};

tmsize_t tiffRead(thandle_t h, void* buf, tmsize_t size) {
    auto* io = static_cast<TiffIo*>(h);
    tmsize_t done = 0;
    while (done < size) {
        const ssize_t n =
            ::read(io->fd, static_cast<char*>(buf) + done, static_cast<std::size_t>(size - done));
        if (n < 0 && errno == EINTR)
            continue;
        if (n < 0) {
            if (io->firstErrno == 0)
                io->firstErrno = errno;
            return -1;
        }
        if (n == 0)
            break;
        done += n;
    }
    return done;
}

tmsize_t tiffWrite(thandle_t h, void* buf, tmsize_t size) {
    auto* io = static_cast<TiffIo*>(h);
    tmsize_t done = 0;
    while (done < size) {
        if (const int fault = gWriteFault.load(); fault != 0) {
            if (io->firstErrno == 0)
                io->firstErrno = fault;
            return -1;
        }
        const ssize_t n = ::write(io->fd, static_cast<const char*>(buf) + done,
                                  static_cast<std::size_t>(size - done));
        if (n < 0 && errno == EINTR)
            continue;
        if (n <= 0) {
            if (io->firstErrno == 0)
                io->firstErrno = n < 0 ? errno : EIO;
            return -1;
        }
        done += n;
    }
    return done;
}

toff_t tiffSeek(thandle_t h, toff_t offset, int whence) {
    auto* io = static_cast<TiffIo*>(h);
    const off_t at = ::lseek(io->fd, static_cast<off_t>(offset), whence);
    if (at < 0) {
        if (io->firstErrno == 0)
            io->firstErrno = errno;
        return static_cast<toff_t>(-1);
    }
    return static_cast<toff_t>(at);
}

int tiffClose(thandle_t /*h*/) {
    return 0; // the descriptor belongs to the caller
}

toff_t tiffSize(thandle_t h) {
    struct stat st {};
    return ::fstat(static_cast<TiffIo*>(h)->fd, &st) == 0 ? static_cast<toff_t>(st.st_size) : 0;
}

int tiffMap(thandle_t, void**, toff_t*) {
    return 0;
}
void tiffUnmap(thandle_t, void*, toff_t) {}

int onTiffError(TIFF*, void* user, const char* module, const char* fmt, va_list ap) {
    auto* io = static_cast<TiffIo*>(user);
    if (io->errors.size() < 2000) {
        std::array<char, 512> text{};
        std::vsnprintf(text.data(), text.size(), fmt, ap);
        io->errors += (io->errors.empty() ? "" : "; ") + std::string(module ? module : "") +
                      (module ? ": " : "") + text.data();
    }
    return 1; // handled: nothing printed
}

int onTiffWarning(TIFF*, void*, const char*, const char*, va_list) {
    return 1;
}

/// Move-only owner of a TIFF* opened over an fd through TiffIo.
class TiffHandle {
public:
    static std::unique_ptr<TiffHandle> open(TiffIo& io, const char* name, const char* mode) {
        TIFFOpenOptions* options = TIFFOpenOptionsAlloc();
        if (options == nullptr)
            return nullptr;
        TIFFOpenOptionsSetErrorHandlerExtR(options, onTiffError, &io);
        TIFFOpenOptionsSetWarningHandlerExtR(options, onTiffWarning, &io);
        TIFF* tif = TIFFClientOpenExt(name, mode, &io, tiffRead, tiffWrite, tiffSeek, tiffClose,
                                      tiffSize, tiffMap, tiffUnmap, options);
        TIFFOpenOptionsFree(options);
        return tif ? std::unique_ptr<TiffHandle>(new TiffHandle(tif)) : nullptr;
    }
    TiffHandle(const TiffHandle&) = delete;
    TiffHandle& operator=(const TiffHandle&) = delete;
    ~TiffHandle() { close(); }
    TIFF* get() const noexcept { return tif_; }
    /// Flushes (when writing) and closes. False when the flush failed.
    bool close() noexcept {
        if (tif_ == nullptr)
            return true;
        const bool flushed = TIFFGetMode(tif_) == O_RDONLY || TIFFFlush(tif_) == 1;
        TIFFClose(tif_);
        tif_ = nullptr;
        return flushed;
    }

private:
    explicit TiffHandle(TIFF* tif) : tif_(tif) {}
    TIFF* tif_ = nullptr;
};

core::Error ioError(const std::string& what, const fs::path& path, const TiffIo& io) {
    const int err = io.firstErrno != 0 ? io.firstErrno : EIO;
    std::string message = what + " " + quoted(path) + ": " + errnoText(err);
    if (!io.errors.empty())
        message += " (libtiff: " + io.errors + ")";
    return makeError(ErrorCode::IoError, message, err);
}

core::Result<void> writeTiff(int fd, const fs::path& tmp, const cv::Mat& image,
                             const std::string& xml, double umPerPx) {
    TiffIo io;
    io.fd = fd;
    auto handle = TiffHandle::open(io, tmp.c_str(), "wl");
    if (!handle)
        return ioError("cannot start TIFF", tmp, io);
    TIFF* tif = handle->get();
    const int channels = image.channels();
    const auto bits = static_cast<std::uint16_t>(image.depth() == CV_16U ? 16 : 8);
    // Rows per strip: about 64 KiB of raw data per strip (the TIFF 6.0 recommendation is ~8 KiB;
    // larger strips compress better and Bio-Formats reads any size).
    const std::size_t rowBytes = static_cast<std::size_t>(image.cols) * image.elemSize();
    const auto rowsPerStrip = static_cast<std::uint32_t>(std::clamp<std::size_t>(
        65536 / std::max<std::size_t>(rowBytes, 1), 1, static_cast<std::size_t>(image.rows)));
    // Resolution tags for readers that ignore the OME-XML (ImageJ's plain TIFF reader).
    const auto pxPerCm = static_cast<float>(1e4 / umPerPx);
    bool ok = TIFFSetField(tif, TIFFTAG_IMAGEWIDTH, static_cast<std::uint32_t>(image.cols)) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_IMAGELENGTH, static_cast<std::uint32_t>(image.rows)) == 1;
    ok =
        ok && TIFFSetField(tif, TIFFTAG_SAMPLESPERPIXEL, static_cast<std::uint16_t>(channels)) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_BITSPERSAMPLE, bits) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_SAMPLEFORMAT, SAMPLEFORMAT_UINT) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_PLANARCONFIG, PLANARCONFIG_CONTIG) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_PHOTOMETRIC,
                            channels == 3 ? PHOTOMETRIC_RGB : PHOTOMETRIC_MINISBLACK) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_COMPRESSION, COMPRESSION_ADOBE_DEFLATE) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_PREDICTOR, PREDICTOR_HORIZONTAL) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_ROWSPERSTRIP, rowsPerStrip) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_IMAGEDESCRIPTION, xml.c_str()) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_SOFTWARE, "slicestation") == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_XRESOLUTION, pxPerCm) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_YRESOLUTION, pxPerCm) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_RESOLUTIONUNIT, RESUNIT_CENTIMETER) == 1;
    if (!ok)
        return ioError("cannot set TIFF tags of", tmp, io);
    // A new Mat: converting into a shallow copy of `image` would swap the caller's pixels.
    cv::Mat rgb;
    if (channels == 3) {
        cv::cvtColor(image, rgb, cv::COLOR_BGR2RGB);
    } else {
        rgb = image;
    }
    // The predictor differences the data in place, so libtiff gets a scratch copy of each strip.
    std::vector<std::uint8_t> strip(rowBytes * rowsPerStrip);
    tstrip_t index = 0;
    for (int y = 0; y < rgb.rows; y += static_cast<int>(rowsPerStrip), ++index) {
        const int rows = std::min(static_cast<int>(rowsPerStrip), rgb.rows - y);
        for (int r = 0; r < rows; ++r) {
            std::memcpy(strip.data() + static_cast<std::size_t>(r) * rowBytes, rgb.ptr(y + r),
                        rowBytes);
        }
        const auto bytes = static_cast<tmsize_t>(static_cast<std::size_t>(rows) * rowBytes);
        if (TIFFWriteEncodedStrip(tif, index, strip.data(), bytes) != bytes) {
            return ioError("cannot write", tmp, io);
        }
    }
    if (!handle->close() || io.firstErrno != 0 || !io.errors.empty()) {
        return ioError("cannot finish", tmp, io);
    }
    return {};
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
    if (hasControlCharacters(info.name) || hasControlCharacters(info.channel)) {
        return makeError(ErrorCode::InvalidArgument,
                         what + "name and channel must not hold control characters");
    }
    return {};
}

core::Result<void> writeAtomic(const fs::path& path, const cv::Mat& image, OmeTiffInfo info) {
    if (auto valid = validate(path, image, info); !valid)
        return valid;
    if (info.acquiredUtc.empty())
        info.acquiredUtc = utcNowIso8601();
    const std::string xml = makeOmeXml(image.cols, image.rows, image.type(), info);

    // Never over an existing file: it may be an image the journal refers to (EEXIST instead).
    auto r = core::replaceAtomically(
        path,
        [&](int fd, const fs::path& tmp) { return writeTiff(fd, tmp, image, xml, info.umPerPx); },
        core::Replace::Never);
    // This writer's contract: a missing directory is an IoError (with ENOENT) like any other.
    if (!r && r.error().code == ErrorCode::NotFound)
        return makeError(ErrorCode::IoError, r.error().message, r.error().sysErrno);
    return r;
}

core::Result<std::string> readDescription(const fs::path& path) {
    core::UniqueFd fd(::open(path.c_str(), O_RDONLY | O_CLOEXEC));
    if (!fd) {
        const int err = errno;
        return makeError(err == ENOENT ? ErrorCode::NotFound : ErrorCode::IoError,
                         "cannot open " + quoted(path) + ": " + errnoText(err), err);
    }
    TiffIo io;
    io.fd = fd.get();
    auto handle = TiffHandle::open(io, path.c_str(), "r");
    if (!handle) {
        return makeError(ErrorCode::IoError, "not a readable TIFF: " + quoted(path) +
                                                 (io.errors.empty() ? "" : " (" + io.errors + ")"));
    }
    const char* description = nullptr;
    if (TIFFGetField(handle->get(), TIFFTAG_IMAGEDESCRIPTION, &description) != 1 ||
        description == nullptr) {
        return makeError(ErrorCode::IoError,
                         "TIFF " + quoted(path) + " has no ImageDescription (not an OME-TIFF)");
    }
    return std::string(description);
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
    gWriteFault.store(err);
}

core::Result<void> writeOmeTiffAtomic(const std::filesystem::path& path, const cv::Mat& image,
                                      const OmeTiffInfo& info) {
    try {
        return writeAtomic(path, image, info);
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::Internal,
                         "cannot write OME-TIFF " + quoted(path) + ": OpenCV: " + e.what());
    } catch (const std::exception& e) {
        return makeError(ErrorCode::Internal,
                         "cannot write OME-TIFF " + quoted(path) + ": " + e.what());
    }
}

} // namespace slicestation::daemon
