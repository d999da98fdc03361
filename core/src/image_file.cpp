#include "slicestation/core/image_file.hpp"

#include "image_limits.hpp"
#include "slicestation/core/atomic_file.hpp"
#include "slicestation/core/codec.hpp"
#include "slicestation/core/tiff_file.hpp"

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <tiffio.h>

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <cstdarg>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <functional>
#include <limits>
#include <memory>
#include <mutex>
#include <new>
#include <optional>
#include <string>
#include <utility>
#include <vector>

namespace slicestation::core {
namespace {

namespace fs = std::filesystem;

std::string quoted(const fs::path& path) {
    return "'" + path.string() + "'";
}

// ---------------------------------------------------------------------------------------------
// libtiff diagnostics: captured, never printed.

/// Diagnostics of one TIFF handle, and the descriptor of one opened over a caller's fd. Its
/// address is the handlers' (and the I/O procedures') user data, so it lives on the heap and
/// does not move while the handle is open.
struct TiffMessages {
    std::string errors;
    std::string warnings;
    int fd = -1;        ///< the caller's descriptor (TiffFile::openFd), or -1
    int firstErrno = 0; ///< errno of the first failed system call on `fd`
};

constexpr std::size_t kMaxMessageChars = 2000; // a corrupt file can emit thousands of warnings

void appendMessage(std::string& out, const char* module, const char* fmt, va_list ap) {
    if (out.size() > kMaxMessageChars) {
        return;
    }
    std::array<char, 512> text{};
    std::vsnprintf(text.data(), text.size(), fmt, ap);
    if (!out.empty()) {
        out += "; ";
    }
    if (module != nullptr && *module != '\0') {
        out += module;
        out += ": ";
    }
    out += text.data();
}

int onTiffError(TIFF* /*tif*/, void* userData, const char* module, const char* fmt, va_list ap) {
    if (userData != nullptr) {
        appendMessage(static_cast<TiffMessages*>(userData)->errors, module, fmt, ap);
    }
    return 1; // handled: libtiff must not fall through to the global (printing) handler
}

int onTiffWarning(TIFF* /*tif*/, void* userData, const char* module, const char* fmt, va_list ap) {
    if (userData != nullptr) {
        appendMessage(static_cast<TiffMessages*>(userData)->warnings, module, fmt, ap);
    }
    return 1;
}

// libtiff may still report through its process-wide handlers when it has no handle (or in
// code paths not converted to the per-handle API). Those messages are kept per thread so that
// concurrent reads do not mix them, and appended to the next error this thread returns.
thread_local std::string tlsGlobalTiffMessages;

void onGlobalTiffMessage(const char* module, const char* fmt, va_list ap) {
    appendMessage(tlsGlobalTiffMessages, module, fmt, ap);
}

void installGlobalTiffHandlers() {
    static std::once_flag once;
    std::call_once(once, [] {
        TIFFSetErrorHandler(onGlobalTiffMessage);
        TIFFSetWarningHandler(onGlobalTiffMessage);
    });
}

// libtiff over a descriptor the caller owns, so that the errno of a failing write (ENOSPC)
// is kept instead of libtiff's bare "write error".

/// errno every write over a descriptor fails with, for tests (0: none).
std::atomic<int> gWriteFault{0};

void keepErrno(TiffMessages& io, int err) {
    if (io.firstErrno == 0)
        io.firstErrno = err;
}

tmsize_t fdRead(thandle_t h, void* buf, tmsize_t size) {
    auto& io = *static_cast<TiffMessages*>(h);
    tmsize_t done = 0;
    while (done < size) {
        const ssize_t n =
            ::read(io.fd, static_cast<char*>(buf) + done, static_cast<std::size_t>(size - done));
        if (n < 0 && errno == EINTR)
            continue;
        if (n < 0) {
            keepErrno(io, errno);
            return -1;
        }
        if (n == 0)
            break;
        done += n;
    }
    return done;
}

tmsize_t fdWrite(thandle_t h, void* buf, tmsize_t size) {
    auto& io = *static_cast<TiffMessages*>(h);
    tmsize_t done = 0;
    while (done < size) {
        if (const int fault = gWriteFault.load(); fault != 0) {
            keepErrno(io, fault);
            return -1;
        }
        const ssize_t n = ::write(io.fd, static_cast<const char*>(buf) + done,
                                  static_cast<std::size_t>(size - done));
        if (n < 0 && errno == EINTR)
            continue;
        if (n <= 0) {
            keepErrno(io, n < 0 ? errno : EIO);
            return -1;
        }
        done += n;
    }
    return done;
}

toff_t fdSeek(thandle_t h, toff_t offset, int whence) {
    auto& io = *static_cast<TiffMessages*>(h);
    const off_t at = ::lseek(io.fd, static_cast<off_t>(offset), whence);
    if (at < 0) {
        keepErrno(io, errno);
        return static_cast<toff_t>(-1);
    }
    return static_cast<toff_t>(at);
}

int fdClose(thandle_t /*h*/) {
    return 0; // the descriptor belongs to the caller
}

toff_t fdSize(thandle_t h) {
    struct stat st {};
    return ::fstat(static_cast<TiffMessages*>(h)->fd, &st) == 0 ? static_cast<toff_t>(st.st_size)
                                                                : 0;
}

int fdMap(thandle_t /*h*/, void** /*base*/, toff_t* /*size*/) {
    return 0; // no mapping: reads go through fdRead
}

void fdUnmap(thandle_t /*h*/, void* /*base*/, toff_t /*size*/) {}

/// Move-only owner of a TIFF* and of the messages its handlers collect: the one libtiff wrapper
/// (readImage, writeImage, writeTiffPage, readTiffDescription).
class TiffFile {
public:
    TiffFile(TiffFile&& other) noexcept
        : tif_(std::exchange(other.tif_, nullptr)), messages_(std::move(other.messages_)) {}
    TiffFile& operator=(TiffFile&&) = delete;
    TiffFile(const TiffFile&) = delete;
    TiffFile& operator=(const TiffFile&) = delete;
    ~TiffFile() { close(); }

    static Result<TiffFile> open(const fs::path& path, const char* mode) {
        installGlobalTiffHandlers();
        tlsGlobalTiffMessages.clear();
        auto messages = std::make_unique<TiffMessages>();
        TIFFOpenOptions* options = TIFFOpenOptionsAlloc();
        if (options == nullptr) {
            return makeError(ErrorCode::Internal, "libtiff: cannot allocate open options");
        }
        TIFFOpenOptionsSetErrorHandlerExtR(options, onTiffError, messages.get());
        TIFFOpenOptionsSetWarningHandlerExtR(options, onTiffWarning, messages.get());
        errno = 0;
        TIFF* tif = TIFFOpenExt(path.c_str(), mode, options);
        const int openErrno = errno;
        TIFFOpenOptionsFree(options);
        if (tif == nullptr) {
            return makeError(ErrorCode::IoError,
                             "cannot open TIFF " + quoted(path) + detail(*messages), openErrno);
        }
        return TiffFile(tif, std::move(messages));
    }

    /// Opens a TIFF over `fd` (owned by the caller, left open); `name` is for messages. Write
    /// errors keep their errno (firstErrno()).
    static Result<TiffFile> openFd(int fd, const fs::path& name, const char* mode) {
        installGlobalTiffHandlers();
        tlsGlobalTiffMessages.clear();
        auto messages = std::make_unique<TiffMessages>();
        messages->fd = fd;
        TIFFOpenOptions* options = TIFFOpenOptionsAlloc();
        if (options == nullptr) {
            return makeError(ErrorCode::Internal, "libtiff: cannot allocate open options");
        }
        TIFFOpenOptionsSetErrorHandlerExtR(options, onTiffError, messages.get());
        TIFFOpenOptionsSetWarningHandlerExtR(options, onTiffWarning, messages.get());
        TIFF* tif = TIFFClientOpenExt(name.c_str(), mode, messages.get(), fdRead, fdWrite, fdSeek,
                                      fdClose, fdSize, fdMap, fdUnmap, options);
        TIFFOpenOptionsFree(options);
        if (tif == nullptr) {
            const int err = messages->firstErrno != 0 ? messages->firstErrno : EIO;
            return makeError(ErrorCode::IoError,
                             "cannot open TIFF " + quoted(name) + detail(*messages), err);
        }
        return TiffFile(tif, std::move(messages));
    }

    TIFF* get() const noexcept { return tif_; }

    /// errno of the first failed system call of a handle opened with openFd (0: none).
    int firstErrno() const noexcept { return messages_ ? messages_->firstErrno : 0; }

    /// Closes the handle (flushing a file opened for writing). False if libtiff reported an
    /// error at any time on this handle.
    bool close() noexcept {
        if (tif_ != nullptr) {
            TIFFClose(tif_);
            tif_ = nullptr;
        }
        return messages_ == nullptr || messages_->errors.empty();
    }

    /// " (libtiff: ...)" with what libtiff reported, or "" when it said nothing.
    std::string detail() const { return messages_ ? detail(*messages_) : std::string(); }

private:
    TiffFile(TIFF* tif, std::unique_ptr<TiffMessages> messages)
        : tif_(tif), messages_(std::move(messages)) {}

    static std::string detail(const TiffMessages& messages) {
        std::string text = messages.errors;
        const std::array<const std::string*, 2> extras{&messages.warnings, &tlsGlobalTiffMessages};
        for (const std::string* extra : extras) {
            if (!extra->empty()) {
                text += (text.empty() ? "" : "; ") + *extra;
            }
        }
        return text.empty() ? std::string() : " (libtiff: " + text + ")";
    }

    TIFF* tif_ = nullptr;
    std::unique_ptr<TiffMessages> messages_;
};

// ---------------------------------------------------------------------------------------------
// Reading

/// Where decoded blocks (strips or tiles) go in the output image.
struct TiffLayout {
    int channels = 1;         ///< channels of the output image (<= 4)
    int sampleBytes = 1;      ///< bytes per sample
    int blockSamples = 1;     ///< interleaved samples per pixel inside one decoded block
    bool swapRedBlue = false; ///< RGB(A) file -> BGR(A) image
};

int outputChannel(const TiffLayout& layout, int sample) {
    return layout.swapRedBlue && sample < 3 ? 2 - sample : sample;
}

/// Copies a decoded block of `rows` x `cols` pixels into `image` at (x0, y0). Block sample k is
/// file sample `firstSample + k`; samples beyond the output's channels are dropped.
void copyBlock(cv::Mat& image, const TiffLayout& layout, const std::uint8_t* block,
               std::size_t blockRowBytes, std::uint32_t x0, std::uint32_t y0, std::uint32_t rows,
               std::uint32_t cols, int firstSample) {
    const auto es = static_cast<std::size_t>(layout.sampleBytes);
    const auto out = static_cast<std::size_t>(layout.channels);
    const auto in = static_cast<std::size_t>(layout.blockSamples);
    const int samples = std::min(layout.blockSamples, layout.channels - firstSample);
    const bool direct = in == out && firstSample == 0 && !layout.swapRedBlue;
    for (std::uint32_t r = 0; r < rows; ++r) {
        const std::uint8_t* src = block + r * blockRowBytes;
        std::uint8_t* dst = image.ptr<std::uint8_t>(static_cast<int>(y0 + r)) + x0 * out * es;
        if (direct) {
            std::memcpy(dst, src, cols * out * es);
            continue;
        }
        for (std::uint32_t c = 0; c < cols; ++c) {
            for (int k = 0; k < samples; ++k) {
                const auto channel =
                    static_cast<std::size_t>(outputChannel(layout, firstSample + k));
                std::memcpy(dst + (c * out + channel) * es,
                            src + (c * in + static_cast<std::size_t>(k)) * es, es);
            }
        }
    }
}

Result<void> readStrips(TIFF* tif, const TiffFile& file, const std::string& where, cv::Mat& image,
                        const TiffLayout& layout, int planes) {
    const auto width = static_cast<std::uint32_t>(image.cols);
    const auto height = static_cast<std::uint32_t>(image.rows);
    std::uint32_t rowsPerStrip = height;
    TIFFGetFieldDefaulted(tif, TIFFTAG_ROWSPERSTRIP, &rowsPerStrip);
    if (rowsPerStrip == 0 || rowsPerStrip > height) {
        rowsPerStrip = height;
    }
    const std::size_t rowBytes = std::size_t{width} *
                                 static_cast<std::size_t>(layout.blockSamples) *
                                 static_cast<std::size_t>(layout.sampleBytes);
    std::vector<std::uint8_t> buffer(rowBytes * rowsPerStrip);
    for (int plane = 0; plane < planes; ++plane) {
        for (std::uint32_t y = 0; y < height; y += rowsPerStrip) {
            const std::uint32_t rows = std::min(rowsPerStrip, height - y);
            const auto strip = TIFFComputeStrip(tif, y, static_cast<std::uint16_t>(plane));
            const auto wanted = static_cast<tmsize_t>(rowBytes * rows);
            const tmsize_t got = TIFFReadEncodedStrip(tif, strip, buffer.data(), wanted);
            if (got < wanted) {
                return makeError(ErrorCode::IoError, where + ": strip " + std::to_string(strip) +
                                                         " is truncated or corrupt" +
                                                         file.detail());
            }
            copyBlock(image, layout, buffer.data(), rowBytes, 0, y, rows, width,
                      planes > 1 ? plane : 0);
        }
    }
    return {};
}

Result<void> readTiles(TIFF* tif, const TiffFile& file, const std::string& where, cv::Mat& image,
                       const TiffLayout& layout, int planes) {
    const auto width = static_cast<std::uint32_t>(image.cols);
    const auto height = static_cast<std::uint32_t>(image.rows);
    std::uint32_t tileWidth = 0;
    std::uint32_t tileHeight = 0;
    if (TIFFGetField(tif, TIFFTAG_TILEWIDTH, &tileWidth) != 1 ||
        TIFFGetField(tif, TIFFTAG_TILELENGTH, &tileHeight) != 1 || tileWidth == 0 ||
        tileHeight == 0) {
        return makeError(ErrorCode::IoError, where + ": tiled image without a valid tile size");
    }
    const std::size_t tileRowBytes = std::size_t{tileWidth} *
                                     static_cast<std::size_t>(layout.blockSamples) *
                                     static_cast<std::size_t>(layout.sampleBytes);
    const auto wanted = static_cast<tmsize_t>(tileRowBytes * tileHeight);
    std::vector<std::uint8_t> buffer(static_cast<std::size_t>(wanted));
    for (int plane = 0; plane < planes; ++plane) {
        for (std::uint32_t y = 0; y < height; y += tileHeight) {
            for (std::uint32_t x = 0; x < width; x += tileWidth) {
                const auto tile = TIFFComputeTile(tif, x, y, 0, static_cast<std::uint16_t>(plane));
                const tmsize_t got = TIFFReadEncodedTile(tif, tile, buffer.data(), wanted);
                if (got < wanted) {
                    return makeError(ErrorCode::IoError, where + ": tile " + std::to_string(tile) +
                                                             " is truncated or corrupt" +
                                                             file.detail());
                }
                copyBlock(image, layout, buffer.data(), tileRowBytes, x, y,
                          std::min(tileHeight, height - y), std::min(tileWidth, width - x),
                          planes > 1 ? plane : 0);
            }
        }
    }
    return {};
}

/// Refuses strips or tiles whose decoded buffer would exceed kMaxImageBytes (a TIFF may
/// declare thousands of samples per pixel or tiles far larger than the image).
Result<void> checkBlockSize(TIFF* tif, const std::string& where, std::uint64_t width,
                            std::uint64_t height, const TiffLayout& layout) {
    std::uint64_t blockWidth = width;
    std::uint64_t blockHeight = height;
    if (TIFFIsTiled(tif) != 0) {
        std::uint32_t tileWidth = 0;
        std::uint32_t tileHeight = 0;
        TIFFGetField(tif, TIFFTAG_TILEWIDTH, &tileWidth);
        TIFFGetField(tif, TIFFTAG_TILELENGTH, &tileHeight);
        blockWidth = tileWidth;
        blockHeight = tileHeight;
    } else {
        std::uint32_t rowsPerStrip = 0;
        TIFFGetFieldDefaulted(tif, TIFFTAG_ROWSPERSTRIP, &rowsPerStrip);
        blockHeight = rowsPerStrip == 0 ? height : std::min<std::uint64_t>(rowsPerStrip, height);
    }
    const std::uint64_t bytes = blockWidth * blockHeight *
                                static_cast<std::uint64_t>(layout.blockSamples) *
                                static_cast<std::uint64_t>(layout.sampleBytes);
    if (bytes > kMaxImageBytes) {
        return makeError(ErrorCode::Unsupported,
                         where + ": one strip or tile of " + std::to_string(blockWidth) + " x " +
                             std::to_string(blockHeight) + " px and " +
                             std::to_string(layout.blockSamples) + " samples (" + megabytes(bytes) +
                             ") exceeds the limit of " + megabytes(kMaxImageBytes));
    }
    return {};
}

/// The most a codec can expand its data, decoded bytes per stored byte: deflate's format limit
/// (1032:1), LZW's with 12-bit codes and a table reset (about 1400:1), PackBits' (64:1), JPEG's
/// (two bits a block at best for each component: under 1024:1 with subsampled chroma); for
/// the other codecs libtiff may have (ZSTD, LZMA, WebP, LERC...), zstd's run-length blocks
/// (about 32000:1).
double maxExpansion(std::uint16_t compression) {
    switch (compression) {
    case COMPRESSION_NONE:
        return 1;
    case COMPRESSION_PACKBITS:
        return 64;
    case COMPRESSION_ADOBE_DEFLATE:
    case COMPRESSION_DEFLATE:
        return 1032;
    case COMPRESSION_LZW:
        return 2000;
    case COMPRESSION_JPEG:
        return 1024;
    default:
        return 40000;
    }
}

/// Refuses an image whose strips or tiles cannot hold what the header claims, before the image
/// is allocated: a few hundred bytes could otherwise claim gigabytes within the size limits and
/// have them allocated, then found missing. Every block must lie inside the file, and the
/// stored bytes they cover (each byte once, so that blocks sharing data do not count twice)
/// times the codec's largest expansion must reach the decoded size.
Result<void> checkStoredData(TIFF* tif, const std::string& where, std::uint64_t decodedBytes,
                             std::uint16_t compression) {
    const std::uint64_t fileSize = TIFFGetSizeProc(tif)(TIFFClientdata(tif));
    const bool tiled = TIFFIsTiled(tif) != 0;
    const std::uint32_t blocks = tiled ? TIFFNumberOfTiles(tif) : TIFFNumberOfStrips(tif);
    std::vector<std::pair<std::uint64_t, std::uint64_t>> ranges;
    ranges.reserve(blocks);
    for (std::uint32_t i = 0; i < blocks; ++i) {
        int err = 0;
        const std::uint64_t offset = TIFFGetStrileOffsetWithErr(tif, i, &err);
        const std::uint64_t count = err == 0 ? TIFFGetStrileByteCountWithErr(tif, i, &err) : 0;
        if (err != 0 || offset > fileSize || count > fileSize - offset) {
            return makeError(ErrorCode::IoError,
                             where + ": " + (tiled ? "tile " : "strip ") + std::to_string(i) +
                                 " lies beyond the end of the file (" + std::to_string(fileSize) +
                                 " bytes): truncated or corrupt");
        }
        if (count > 0)
            ranges.emplace_back(offset, offset + count);
    }
    std::sort(ranges.begin(), ranges.end());
    std::uint64_t stored = 0;
    std::uint64_t end = 0;
    for (const auto& [from, to] : ranges) {
        const std::uint64_t start = std::max(from, end);
        if (to > start)
            stored += to - start;
        end = std::max(end, to);
    }
    const double reach = static_cast<double>(stored) * maxExpansion(compression);
    if (reach < static_cast<double>(decodedBytes)) {
        return makeError(ErrorCode::IoError,
                         where + ": the header claims " + megabytes(decodedBytes) +
                             " of pixels but the file stores " + std::to_string(stored) +
                             " bytes of image data, more than compression scheme " +
                             std::to_string(compression) + " can expand (truncated or hostile)");
    }
    return {};
}

/// Reads the current directory (page) of `tif`.
Result<cv::Mat> readPage(TIFF* tif, const TiffFile& file, const std::string& where) {
    std::uint32_t width = 0;
    std::uint32_t height = 0;
    if (TIFFGetField(tif, TIFFTAG_IMAGEWIDTH, &width) != 1 ||
        TIFFGetField(tif, TIFFTAG_IMAGELENGTH, &height) != 1 || width == 0 || height == 0) {
        return makeError(ErrorCode::IoError, where + ": missing or zero image width/length");
    }
    if (width > static_cast<std::uint32_t>(std::numeric_limits<int>::max()) ||
        height > static_cast<std::uint32_t>(std::numeric_limits<int>::max())) {
        return makeError(ErrorCode::Unsupported, where + ": image too large");
    }
    std::uint16_t samples = 1;
    std::uint16_t bits = 1;
    std::uint16_t format = SAMPLEFORMAT_UINT;
    std::uint16_t planar = PLANARCONFIG_CONTIG;
    std::uint16_t photometric = PHOTOMETRIC_MINISBLACK;
    std::uint16_t compression = COMPRESSION_NONE;
    TIFFGetFieldDefaulted(tif, TIFFTAG_SAMPLESPERPIXEL, &samples);
    TIFFGetFieldDefaulted(tif, TIFFTAG_BITSPERSAMPLE, &bits);
    TIFFGetFieldDefaulted(tif, TIFFTAG_SAMPLEFORMAT, &format);
    TIFFGetFieldDefaulted(tif, TIFFTAG_PLANARCONFIG, &planar);
    TIFFGetFieldDefaulted(tif, TIFFTAG_COMPRESSION, &compression);
    if (TIFFGetField(tif, TIFFTAG_PHOTOMETRIC, &photometric) != 1) {
        photometric = samples >= 3 ? PHOTOMETRIC_RGB : PHOTOMETRIC_MINISBLACK;
    }
    if (samples == 0) {
        return makeError(ErrorCode::IoError, where + ": SamplesPerPixel is 0");
    }
    if (TIFFIsCODECConfigured(compression) != 1) {
        return makeError(ErrorCode::Unsupported, where + ": compression scheme " +
                                                     std::to_string(compression) +
                                                     " is not available in libtiff");
    }
    if (photometric == PHOTOMETRIC_PALETTE) {
        return makeError(ErrorCode::Unsupported, where + ": palette (colour-mapped) images");
    }
    if (photometric == PHOTOMETRIC_YCBCR) {
        if (compression != COMPRESSION_JPEG) {
            return makeError(ErrorCode::Unsupported, where + ": YCbCr images without JPEG");
        }
        // The JPEG codec converts to RGB itself when asked to.
        TIFFSetField(tif, TIFFTAG_JPEGCOLORMODE, JPEGCOLORMODE_RGB);
        photometric = PHOTOMETRIC_RGB;
    }

    int depth = -1;
    const bool unsignedSamples = format == SAMPLEFORMAT_UINT || format == SAMPLEFORMAT_VOID;
    if (unsignedSamples && bits == 8) {
        depth = CV_8U;
    } else if (unsignedSamples && bits == 16) {
        depth = CV_16U;
    } else if ((unsignedSamples || format == SAMPLEFORMAT_INT) && bits == 32) {
        depth = CV_32S;
    } else if (format == SAMPLEFORMAT_IEEEFP && bits == 32) {
        depth = CV_32F;
    } else {
        return makeError(ErrorCode::Unsupported,
                         where + ": " + std::to_string(bits) + "-bit samples of SampleFormat " +
                             std::to_string(format) +
                             " (supported: uint8, uint16, int32, uint32, float32)");
    }

    TiffLayout layout;
    layout.channels = std::min<int>(samples, 4);
    layout.sampleBytes = bits / 8;
    const bool separate = planar == PLANARCONFIG_SEPARATE && samples > 1;
    layout.blockSamples = separate ? 1 : samples;
    layout.swapRedBlue = photometric == PHOTOMETRIC_RGB && layout.channels >= 3;
    const int planes = separate ? layout.channels : 1; // planes beyond the 4th are not read

    // Bounded from the header, before anything is allocated or decoded: a few kilobytes of
    // deflate can claim gigapixels.
    if (auto fits = checkImageSize(where, width, height, layout.channels, layout.sampleBytes);
        !fits) {
        return fits.error();
    }
    if (auto fits = checkBlockSize(tif, where, width, height, layout); !fits) {
        return fits.error();
    }
    const std::uint64_t decodedBytes = std::uint64_t{width} * height *
                                       static_cast<std::uint64_t>(planes > 1 ? planes : samples) *
                                       static_cast<std::uint64_t>(layout.sampleBytes);
    if (auto held = checkStoredData(tif, where, decodedBytes, compression); !held) {
        return held.error();
    }
    cv::Mat image(static_cast<int>(height), static_cast<int>(width),
                  CV_MAKETYPE(depth, layout.channels));
    const Result<void> read = TIFFIsTiled(tif) != 0
                                  ? readTiles(tif, file, where, image, layout, planes)
                                  : readStrips(tif, file, where, image, layout, planes);
    if (!read) {
        return read.error();
    }

    if (depth == CV_32S && unsignedSamples) {
        // uint32 samples share CV_32S with int32: values above INT32_MAX would turn negative.
        for (int y = 0; y < image.rows; ++y) {
            const auto* row = image.ptr<std::int32_t>(y);
            const auto count = static_cast<std::size_t>(image.cols) * layout.channels;
            const auto* bad = std::find_if(row, row + count, [](std::int32_t v) { return v < 0; });
            if (bad != row + count) {
                return makeError(ErrorCode::Unsupported,
                                 where + ": uint32 value above INT32_MAX in row " +
                                     std::to_string(y));
            }
        }
    }
    return image;
}

/// Channel count an ImageJ hyperstack declares in its ImageDescription ("ImageJ=1.54g\n
/// channels=2\n..."), or 1 when the file is not one. ImageJ stores each channel as a page.
int imageJChannels(TIFF* tif) {
    const char* description = nullptr;
    if (TIFFGetField(tif, TIFFTAG_IMAGEDESCRIPTION, &description) != 1 || description == nullptr ||
        std::strncmp(description, "ImageJ=", 7) != 0) {
        return 1;
    }
    const char* channels = std::strstr(description, "\nchannels=");
    if (channels == nullptr) {
        return 1;
    }
    const long count = std::strtol(channels + std::strlen("\nchannels="), nullptr, 10);
    return count > 1 ? static_cast<int>(std::min<long>(count, 1 << 16)) : 1;
}

Result<cv::Mat> readTiff(const fs::path& path) {
    auto file = TiffFile::open(path, "r");
    if (!file) {
        return file.error();
    }
    TIFF* tif = file->get();
    const std::string where = "TIFF " + quoted(path);
    auto first = readPage(tif, *file, where);
    if (!first) {
        return first;
    }
    const int channels = imageJChannels(tif);
    if (channels == 1 || first->channels() != 1) {
        return first; // an ordinary (multi-page) TIFF: the first page
    }
    // ImageJ hyperstack: pages 0..C-1 are the channels of the first slice and frame.
    const int pages = std::min(channels, 4);
    if (auto fits = checkImageSize(where, static_cast<std::uint64_t>(first->cols),
                                   static_cast<std::uint64_t>(first->rows), pages,
                                   static_cast<int>(first->elemSize1()));
        !fits) {
        return fits.error();
    }
    std::vector<cv::Mat> planes{std::move(first.value())};
    for (int c = 1; c < pages; ++c) {
        if (TIFFReadDirectory(tif) != 1) {
            return makeError(ErrorCode::IoError, where + ": ImageJ description declares " +
                                                     std::to_string(channels) +
                                                     " channels, but page " + std::to_string(c) +
                                                     " is missing" + file->detail());
        }
        auto page = readPage(tif, *file, where);
        if (!page) {
            return page;
        }
        if (page->size() != planes.front().size() || page->type() != planes.front().type()) {
            return makeError(ErrorCode::IoError, where + ": ImageJ channel page " +
                                                     std::to_string(c) +
                                                     " differs in size or type from page 0");
        }
        planes.push_back(std::move(page.value()));
    }
    cv::Mat image;
    cv::merge(planes, image);
    return image;
}

/// Width and height from a PNG's IHDR chunk (PNG spec, section 11.2.2), with the bytes a pixel
/// decodes to; nullopt when `path` is not a PNG.
struct PngHeader {
    std::uint64_t width = 0, height = 0;
    int channels = 1, sampleBytes = 1;
    /// Bits a pixel takes before decoding (a palette index, 1-bit grey...): what the
    /// compressed stream holds, as opposed to channels x sampleBytes after decoding.
    int storedBitsPerPixel = 8;
    /// The codec's largest expansion of one stored byte (0: no useful bound).
    double maxExpansion = 0;
};

std::optional<PngHeader> readPngHeader(const fs::path& path) {
    std::array<unsigned char, 26> h{};
    std::ifstream in(path, std::ios::binary);
    in.read(reinterpret_cast<char*>(h.data()), static_cast<std::streamsize>(h.size()));
    static constexpr std::array<unsigned char, 8> kSignature{0x89, 'P',  'N',  'G',
                                                             '\r', '\n', 0x1A, '\n'};
    if (in.gcount() != static_cast<std::streamsize>(h.size()) ||
        !std::equal(kSignature.begin(), kSignature.end(), h.begin()) ||
        std::memcmp(h.data() + 12, "IHDR", 4) != 0) {
        return std::nullopt;
    }
    const auto be32 = [&](std::size_t at) {
        return (std::uint64_t{h[at]} << 24) | (std::uint64_t{h[at + 1]} << 16) |
               (std::uint64_t{h[at + 2]} << 8) | std::uint64_t{h[at + 3]};
    };
    PngHeader png;
    png.width = be32(16);
    png.height = be32(20);
    const int bitDepth = h[24];
    const int colourType = h[25];
    png.sampleBytes = bitDepth > 8 ? 2 : 1;
    // 0 grey, 2 RGB, 3 palette (decoded to BGR), 4 grey + alpha, 6 RGBA.
    png.channels = colourType == 2 || colourType == 3 ? 3
                   : colourType == 4                  ? 2
                   : colourType == 6                  ? 4
                                                      : 1;
    const int storedSamples = colourType == 2 ? 3 : colourType == 4 ? 2 : colourType == 6 ? 4 : 1;
    png.storedBitsPerPixel = std::max(1, bitDepth) * storedSamples;
    png.maxExpansion = 1032; // zlib's deflate: at most 1032:1
    return png;
}

/// Width, height and components from a baseline or progressive JPEG's frame header (the first
/// SOFn marker, ITU T.81 B.2.2) in `h`; nullopt when it is not a JPEG or has no frame header.
/// readJpegHeader looks in a file's first 1 MiB.
std::optional<PngHeader> jpegHeader(const unsigned char* h, std::size_t size) {
    if (size < 4 || h[0] != 0xFF || h[1] != 0xD8) {
        return std::nullopt;
    }
    std::size_t at = 2;
    while (at + 9 < size) {
        if (h[at] != 0xFF) {
            return std::nullopt;
        }
        const unsigned marker = h[at + 1];
        if (marker == 0xFF) { // fill byte
            ++at;
            continue;
        }
        const std::size_t length = (std::size_t{h[at + 2]} << 8) | h[at + 3];
        const bool frame =
            marker >= 0xC0 && marker <= 0xCF && marker != 0xC4 && marker != 0xC8 && marker != 0xCC;
        if (frame) {
            PngHeader jpeg;
            jpeg.height = (std::uint64_t{h[at + 5]} << 8) | h[at + 6];
            jpeg.width = (std::uint64_t{h[at + 7]} << 8) | h[at + 8];
            jpeg.channels = h[at + 9] >= 3 ? 3 : 1;
            jpeg.sampleBytes = 1;
            jpeg.storedBitsPerPixel = 8 * jpeg.channels;
            // Sequential Huffman coding spends at least two bits (DC, end of block) on each 8 x 8
            // block of each component: under 1024:1 even with chroma subsampled 4 x 4.
            // Progressive scans can end thousands of blocks with one code, but the DC scan still
            // spends a bit a block: under 2048:1. Arithmetic coding (SOF9..SOF15) has no floor.
            const bool progressive = marker == 0xC2 || marker == 0xC6;
            jpeg.maxExpansion = marker >= 0xC9 ? 0 : progressive ? 2048 : 1024;
            return jpeg;
        }
        if (length < 2) {
            return std::nullopt;
        }
        at += 2 + length;
    }
    return std::nullopt;
}

std::optional<PngHeader> readJpegHeader(const fs::path& path) {
    std::ifstream in(path, std::ios::binary);
    std::vector<unsigned char> h(1 << 20);
    in.read(reinterpret_cast<char*>(h.data()), static_cast<std::streamsize>(h.size()));
    return jpegHeader(h.data(), static_cast<std::size_t>(in.gcount()));
}

/// Refuses a compressed file too small to hold the pixels its header claims, given the most its
/// codec turns one stored byte into. Checked before the decoder allocates the image, which it does
/// from the header alone.
Result<void> checkFileHolds(const fs::path& path, const char* format, const PngHeader& header) {
    std::error_code ec;
    const std::uint64_t fileSize = fs::file_size(path, ec);
    const double stored =
        static_cast<double>(header.height) *
        std::ceil(static_cast<double>(header.width) * header.storedBitsPerPixel / 8.0);
    if (!ec && header.maxExpansion > 0 &&
        static_cast<double>(fileSize) * header.maxExpansion < stored) {
        return makeError(
            ErrorCode::IoError,
            std::string(format) + " " + quoted(path) + ": the header claims " +
                std::to_string(header.width) + " x " + std::to_string(header.height) +
                " px but the file has only " + std::to_string(fileSize) +
                " bytes, fewer than its compression can expand (truncated or hostile)");
    }
    return {};
}

Result<cv::Mat> readPngOrJpeg(const fs::path& path) {
    // PNG and JPEG are decoded by libpng and libjpeg-turbo (codec.hpp) once their headers are
    // checked against our own limits and against what the file can hold: the decoders allocate
    // the image from the header alone. No other format is read (OpenCV's other decoders,
    // Radiance HDR, JPEG 2000, PNM, GDAL's hundred formats, allocated up to 2^30 px of floats
    // for a 60-byte file claiming them). Sections, label images and captures come as TIFF, PNG
    // or JPEG.
    const auto png = readPngHeader(path);
    const auto jpeg = png ? std::nullopt : readJpegHeader(path);
    if (png) {
        if (auto fits = checkImageSize("PNG " + quoted(path), png->width, png->height,
                                       png->channels, png->sampleBytes);
            !fits) {
            return fits.error();
        }
        if (auto held = checkFileHolds(path, "PNG", *png); !held) {
            return held.error();
        }
    } else if (jpeg) {
        if (auto fits = checkImageSize("JPEG " + quoted(path), jpeg->width, jpeg->height,
                                       jpeg->channels, jpeg->sampleBytes);
            !fits) {
            return fits.error();
        }
        if (jpeg->maxExpansion <= 0) {
            // Arithmetic coding has no floor on the bits a block takes, so a few bytes could
            // claim gigabytes; no camera or slide scanner writes it.
            return makeError(ErrorCode::Unsupported,
                             "JPEG " + quoted(path) +
                                 " is arithmetic-coded (SOF9..SOF15), which is not read");
        }
        if (auto held = checkFileHolds(path, "JPEG", *jpeg); !held) {
            return held.error();
        }
    } else {
        return makeError(ErrorCode::IoError,
                         "image " + quoted(path) +
                             " is not a TIFF, PNG or JPEG file (or its header is corrupt or "
                             "truncated); sections and label images are read in those formats");
    }
    std::ifstream in(path, std::ios::binary);
    std::error_code ec;
    const std::uint64_t fileSize = fs::file_size(path, ec);
    if (!in || ec) {
        return makeError(ErrorCode::IoError, "cannot read image " + quoted(path));
    }
    // The header checks above bound the pixels; the file's own size is bounded alike (a PNG or
    // JPEG never needs more bytes than its pixels take uncompressed, plus slack for metadata).
    if (fileSize > kMaxImageBytes + (std::uint64_t{64} << 20)) {
        return makeError(ErrorCode::Unsupported,
                         "image " + quoted(path) + ": a file of " + megabytes(fileSize) +
                             " exceeds the limit of " + megabytes(kMaxImageBytes));
    }
    std::vector<std::uint8_t> bytes(static_cast<std::size_t>(fileSize));
    in.read(reinterpret_cast<char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
    if (in.gcount() != static_cast<std::streamsize>(bytes.size())) {
        return makeError(ErrorCode::IoError,
                         "cannot read image " + quoted(path) + " (it changed while being read)");
    }
    if (png) {
        return decodePng(bytes, "PNG " + quoted(path));
    }
    return decodeJpeg(bytes, JpegPixels::AsStored, "JPEG " + quoted(path));
}

bool hasTiffMagic(const std::array<char, 4>& m) {
    const bool little = m[0] == 'I' && m[1] == 'I' && (m[2] == 42 || m[2] == 43) && m[3] == 0;
    const bool big = m[0] == 'M' && m[1] == 'M' && m[2] == 0 && (m[3] == 42 || m[3] == 43);
    return little || big;
}

// ---------------------------------------------------------------------------------------------
// Writing

/// BGR(A) -> RGB(A) for any depth (cv::cvtColor does not take CV_32S).
cv::Mat toRgbOrder(const cv::Mat& image) {
    if (image.channels() < 3) {
        return image;
    }
    cv::Mat rgb(image.size(), image.type());
    const std::array<int, 8> fromTo{0, 2, 1, 1, 2, 0, 3, 3};
    cv::mixChannels(&image, 1, &rgb, 1, fromTo.data(), static_cast<std::size_t>(image.channels()));
    return rgb;
}

/// IoError for `what` on `name`, with the errno of the first failed system call (EIO when
/// libtiff failed without one) and what libtiff said.
Error writeError(const std::string& what, const fs::path& name, const TiffFile& file) {
    const int err = file.firstErrno() != 0 ? file.firstErrno() : EIO;
    return makeError(ErrorCode::IoError,
                     what + " " + quoted(name) + ": " + std::strerror(err) + " (errno " +
                         std::to_string(err) + ")" + file.detail(),
                     err);
}

/// Tags of one page: strips of `rowsPerStrip` rows, or square tiles of `tilePx` when it is > 0.
Result<void> setPageTags(TIFF* tif, const cv::Mat& image, const TiffTags& tags,
                         std::uint32_t rowsPerStrip, std::uint32_t tilePx = 0) {
    const int channels = image.channels();
    const int depth = image.depth();
    const auto bits = static_cast<std::uint16_t>(8 * CV_ELEM_SIZE1(depth));
    const std::uint16_t format = depth == CV_32F ? SAMPLEFORMAT_IEEEFP : SAMPLEFORMAT_UINT;
    const std::uint16_t photometric = channels >= 3 ? PHOTOMETRIC_RGB : PHOTOMETRIC_MINISBLACK;

    bool ok = TIFFSetField(tif, TIFFTAG_IMAGEWIDTH, static_cast<std::uint32_t>(image.cols)) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_IMAGELENGTH, static_cast<std::uint32_t>(image.rows)) == 1;
    ok =
        ok && TIFFSetField(tif, TIFFTAG_SAMPLESPERPIXEL, static_cast<std::uint16_t>(channels)) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_BITSPERSAMPLE, bits) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_SAMPLEFORMAT, format) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_PLANARCONFIG, PLANARCONFIG_CONTIG) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_PHOTOMETRIC, photometric) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_COMPRESSION, COMPRESSION_ADOBE_DEFLATE) == 1;
    ok = ok && TIFFSetField(tif, TIFFTAG_PREDICTOR,
                            depth == CV_32F ? PREDICTOR_FLOATINGPOINT : PREDICTOR_HORIZONTAL) == 1;
    if (channels == 2 || channels == 4) {
        const std::uint16_t extra =
            channels == 4 ? EXTRASAMPLE_UNASSALPHA : EXTRASAMPLE_UNSPECIFIED;
        ok = ok && TIFFSetField(tif, TIFFTAG_EXTRASAMPLES, 1, &extra) == 1;
    }
    if (tilePx > 0) {
        ok = ok && TIFFSetField(tif, TIFFTAG_TILEWIDTH, tilePx) == 1;
        ok = ok && TIFFSetField(tif, TIFFTAG_TILELENGTH, tilePx) == 1;
    } else {
        ok = ok && TIFFSetField(tif, TIFFTAG_ROWSPERSTRIP, rowsPerStrip) == 1;
    }
    if (!tags.imageDescription.empty())
        ok = ok && TIFFSetField(tif, TIFFTAG_IMAGEDESCRIPTION, tags.imageDescription.c_str()) == 1;
    if (!tags.software.empty())
        ok = ok && TIFFSetField(tif, TIFFTAG_SOFTWARE, tags.software.c_str()) == 1;
    if (tags.umPerPx > 0) {
        // For readers that ignore the OME-XML (ImageJ's plain TIFF reader).
        const auto pxPerCm = static_cast<float>(1e4 / tags.umPerPx);
        ok = ok && TIFFSetField(tif, TIFFTAG_XRESOLUTION, pxPerCm) == 1;
        ok = ok && TIFFSetField(tif, TIFFTAG_YRESOLUTION, pxPerCm) == 1;
        ok = ok && TIFFSetField(tif, TIFFTAG_RESOLUTIONUNIT, RESUNIT_CENTIMETER) == 1;
    }
    if (!ok)
        return makeError(ErrorCode::Internal, "libtiff refused a tag");
    return {};
}

Result<void> writeTiffPageImpl(int fd, const fs::path& name, const cv::Mat& image,
                               const TiffTags& tags) {
    auto file = TiffFile::openFd(fd, name, "wl");
    if (!file) {
        return file.error();
    }
    TIFF* tif = file->get();
    // Rows per strip: about 64 KiB of raw data per strip (the TIFF 6.0 recommendation is ~8 KiB;
    // larger strips compress better and Bio-Formats reads any size).
    const std::size_t rowBytes = static_cast<std::size_t>(image.cols) * image.elemSize();
    const auto rowsPerStrip = static_cast<std::uint32_t>(std::clamp<std::size_t>(
        65536 / std::max<std::size_t>(rowBytes, 1), 1, static_cast<std::size_t>(image.rows)));
    if (auto set = setPageTags(tif, image, tags, rowsPerStrip); !set) {
        return makeError(ErrorCode::Internal,
                         "cannot set TIFF tags for " + quoted(name) + file->detail());
    }
    const cv::Mat rgb = toRgbOrder(image);
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
            return writeError("cannot write TIFF", name, *file);
        }
    }
    if (!file->close() || file->firstErrno() != 0) {
        return writeError("cannot finish TIFF", name, *file);
    }
    return {};
}

// ---------------------------------------------------------------------------------------------
// Tiled pyramids (OME-TIFF sub-resolutions in SubIFDs)

/// Writes `rgb` (already in file sample order) as the tiles of the current directory.
Result<void> writeTiles(TIFF* tif, const TiffFile& file, const fs::path& name, const cv::Mat& rgb,
                        int tilePx) {
    const std::size_t pixelBytes = rgb.elemSize();
    const std::size_t tileRowBytes = static_cast<std::size_t>(tilePx) * pixelBytes;
    // The predictor differences the data in place: libtiff gets a scratch buffer per tile.
    std::vector<std::uint8_t> tile(tileRowBytes * static_cast<std::size_t>(tilePx));
    for (int y = 0; y < rgb.rows; y += tilePx) {
        for (int x = 0; x < rgb.cols; x += tilePx) {
            std::fill(tile.begin(), tile.end(), std::uint8_t{0}); // edge tiles: zero padding
            const int rows = std::min(tilePx, rgb.rows - y);
            const std::size_t rowBytes =
                static_cast<std::size_t>(std::min(tilePx, rgb.cols - x)) * pixelBytes;
            for (int r = 0; r < rows; ++r)
                std::memcpy(tile.data() + static_cast<std::size_t>(r) * tileRowBytes,
                            rgb.ptr(y + r) + static_cast<std::size_t>(x) * pixelBytes, rowBytes);
            const ttile_t index = TIFFComputeTile(tif, static_cast<std::uint32_t>(x),
                                                  static_cast<std::uint32_t>(y), 0, 0);
            const auto bytes = static_cast<tmsize_t>(tile.size());
            if (TIFFWriteEncodedTile(tif, index, tile.data(), bytes) != bytes)
                return writeError("cannot write TIFF", name, file);
        }
    }
    return {};
}

Result<void> checkPyramidArguments(const fs::path& name, const cv::Mat& image, const TiffTags& tags,
                                   const TiffPyramidLayout& layout) {
    const std::string what = "cannot write TIFF " + quoted(name) + ": ";
    const int depth = image.depth();
    if (image.empty() || (depth != CV_8U && depth != CV_16U) ||
        (image.channels() != 1 && image.channels() != 3)) {
        return makeError(
            ErrorCode::Unsupported,
            what + "a pyramid takes 8/16-bit images with 1 or 3 channels, not " +
                (image.empty() ? std::string("an empty image") : cv::typeToString(image.type())));
    }
    if (layout.tileSizePx < 16 || layout.tileSizePx > 4096 || layout.tileSizePx % 16 != 0) {
        return makeError(ErrorCode::InvalidArgument,
                         what + "tile size " + std::to_string(layout.tileSizePx) +
                             " px (a multiple of 16 in [16, 4096], as TIFF 6.0 asks)");
    }
    if (layout.maxTopSidePx < 1) {
        return makeError(ErrorCode::InvalidArgument, what + "maxTopSidePx must be >= 1");
    }
    if (tags.imageDescription.find('\0') != std::string::npos) {
        return makeError(ErrorCode::InvalidArgument, what + "ImageDescription holds a NUL");
    }
    return {};
}

Result<void> writeTiffPyramidImpl(int fd, const fs::path& name, const cv::Mat& image,
                                  const TiffTags& tags, const TiffPyramidLayout& layout) {
    const std::vector<cv::Size> levels = tiffPyramidLevels(image.size(), layout.maxTopSidePx);
    std::uint64_t rawBytes = 0;
    for (const cv::Size& s : levels)
        rawBytes += static_cast<std::uint64_t>(s.area()) * image.elemSize();
    const bool big =
        layout.bigTiff == TiffPyramidLayout::BigTiff::Always ||
        (layout.bigTiff == TiffPyramidLayout::BigTiff::Auto && rawBytes > layout.bigTiffAboveBytes);
    auto file = TiffFile::openFd(fd, name, big ? "wl8" : "wl");
    if (!file)
        return file.error();
    TIFF* tif = file->get();
    const auto tilePx = static_cast<std::uint32_t>(layout.tileSizePx);
    if (auto set = setPageTags(tif, image, tags, 0, tilePx); !set)
        return makeError(ErrorCode::Internal,
                         "cannot set TIFF tags for " + quoted(name) + file->detail());
    // Zero offsets as placeholders: libtiff writes the next levels.size() - 1 directories as
    // this page's SubIFDs and fills their offsets in (TIFFTAG_SUBIFD in libtiff's tif_dir.c).
    std::vector<toff_t> subIfds(levels.size() - 1, 0);
    if (!subIfds.empty() &&
        TIFFSetField(tif, TIFFTAG_SUBIFD, static_cast<std::uint16_t>(subIfds.size()),
                     subIfds.data()) != 1)
        return makeError(ErrorCode::Internal,
                         "cannot set the SubIFD tag of " + quoted(name) + file->detail());
    if (auto w = writeTiles(tif, *file, name, toRgbOrder(image), layout.tileSizePx); !w)
        return w;
    if (TIFFWriteDirectory(tif) != 1)
        return writeError("cannot write the TIFF directory of", name, *file);
    for (std::size_t k = 1; k < levels.size(); ++k) {
        cv::Mat reduced;
        cv::resize(image, reduced, levels[k], 0, 0, cv::INTER_AREA);
        TiffTags levelTags;
        levelTags.software = tags.software;
        if (tags.umPerPx > 0)
            levelTags.umPerPx = tags.umPerPx * image.cols / static_cast<double>(reduced.cols);
        bool ok = TIFFSetField(tif, TIFFTAG_SUBFILETYPE, FILETYPE_REDUCEDIMAGE) == 1;
        ok = ok && static_cast<bool>(setPageTags(tif, reduced, levelTags, 0, tilePx));
        if (!ok)
            return makeError(ErrorCode::Internal,
                             "cannot set TIFF tags for " + quoted(name) + file->detail());
        if (auto w = writeTiles(tif, *file, name, toRgbOrder(reduced), layout.tileSizePx); !w)
            return w;
        if (TIFFWriteDirectory(tif) != 1)
            return writeError("cannot write a reduced level of", name, *file);
    }
    if (!file->close() || file->firstErrno() != 0)
        return writeError("cannot finish TIFF", name, *file);
    return {};
}

/// Opens `path` and makes `level` (0: first page, k: its k-th SubIFD) the current directory.
Result<TiffFile> openLevel(const fs::path& path, int level) {
    std::error_code ec;
    if (!fs::exists(path, ec))
        return makeError(ErrorCode::NotFound, "TIFF " + quoted(path) + " does not exist");
    auto file = TiffFile::open(path, "r");
    if (!file)
        return makeError(ErrorCode::IoError, "not a readable TIFF: " + file.error().message,
                         file.error().sysErrno);
    if (level == 0)
        return file;
    TIFF* tif = file->get();
    std::uint16_t count = 0;
    toff_t* offsets = nullptr;
    if (level < 0 || TIFFGetField(tif, TIFFTAG_SUBIFD, &count, &offsets) != 1 || level > count)
        return makeError(ErrorCode::NotFound, "TIFF " + quoted(path) + " has no level " +
                                                  std::to_string(level) + " (it has " +
                                                  std::to_string(count + 1) + ")");
    if (TIFFSetSubDirectory(tif, offsets[level - 1]) != 1)
        return makeError(ErrorCode::IoError, "TIFF " + quoted(path) + ": cannot read level " +
                                                 std::to_string(level) + file->detail());
    return file;
}

std::string lowerExtension(const fs::path& path) {
    std::string ext = path.extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(),
                   [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
    return ext;
}

Result<void> writeImageImpl(const fs::path& path, const cv::Mat& image) {
    const std::string ext = lowerExtension(path);
    const int depth = image.depth();
    const int channels = image.channels();
    const std::string what = "cannot write " + quoted(path) + ": ";
    if (ext == ".png") {
        if ((depth != CV_8U && depth != CV_16U) || channels == 2 || channels > 4) {
            return makeError(ErrorCode::Unsupported,
                             what + "PNG takes 8/16-bit images with 1, 3 or 4 channels, not " +
                                 cv::typeToString(image.type()));
        }
        auto bytes = encodePng(image);
        if (!bytes) {
            return makeError(ErrorCode::Internal, what + bytes.error().message);
        }
        return writeFileAtomically(
            path, std::string_view(reinterpret_cast<const char*>(bytes->data()), bytes->size()));
    }
    if (ext == ".tif" || ext == ".tiff") {
        if ((depth != CV_8U && depth != CV_16U && depth != CV_32S && depth != CV_32F) ||
            channels > 4) {
            return makeError(ErrorCode::Unsupported,
                             what + "TIFF takes 8U, 16U, 32S or 32F with 1..4 channels, not " +
                                 cv::typeToString(image.type()));
        }
        if (depth == CV_32S) {
            double minValue = 0;
            cv::Point where;
            cv::minMaxLoc(image.reshape(1), &minValue, nullptr, &where, nullptr);
            if (minValue < 0) {
                return makeError(ErrorCode::InvalidArgument,
                                 what + "CV_32S is written as uint32 labels, but row " +
                                     std::to_string(where.y) + " holds " +
                                     std::to_string(static_cast<long long>(minValue)));
            }
        }
        return replaceAtomically(path, [&](int fd, const fs::path& /*tmp*/) {
            return writeTiffPageImpl(fd, path, image, {});
        });
    }
    return makeError(ErrorCode::Unsupported, what + "unknown extension '" +
                                                 path.extension().string() +
                                                 "' (use .png, .tif or .tiff)");
}

} // namespace

Result<cv::Mat> readImage(const std::filesystem::path& path) {
    std::error_code ec;
    const auto status = fs::status(path, ec);
    if (!fs::exists(status)) {
        return makeError(ErrorCode::NotFound, "image file " + quoted(path) + " does not exist");
    }
    if (fs::is_directory(status)) {
        return makeError(ErrorCode::IoError, quoted(path) + " is a directory, not an image");
    }
    std::array<char, 4> magic{};
    std::streamsize magicBytes = 0;
    {
        std::ifstream in(path, std::ios::binary);
        if (!in.is_open()) {
            const int err = errno;
            return makeError(ErrorCode::IoError,
                             "cannot open image " + quoted(path) + ": " + std::strerror(err), err);
        }
        in.read(magic.data(), static_cast<std::streamsize>(magic.size()));
        magicBytes = in.gcount();
    }
    if (magicBytes == 0) {
        return makeError(ErrorCode::IoError, "image file " + quoted(path) + " is empty");
    }
    try {
        auto image = magicBytes == 4 && hasTiffMagic(magic) ? readTiff(path) : readPngOrJpeg(path);
        if (image && image->depth() == CV_32F) {
            // NaN and infinity are no intensity: every threshold and mean downstream would turn
            // into nonsense without an error.
            cv::Point where;
            if (!cv::checkRange(image->reshape(1), true, &where)) {
                return makeError(ErrorCode::InvalidArgument,
                                 "image " + quoted(path) + ": NaN or infinite pixel at x=" +
                                     std::to_string(where.x / image->channels()) +
                                     ", y=" + std::to_string(where.y) +
                                     " (float images must hold finite values)");
            }
        }
        return image;
    } catch (const std::bad_alloc&) {
        return makeError(ErrorCode::IoError, "image " + quoted(path) + " is too large to load");
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::IoError, "cannot read image " + quoted(path) + ": " + e.what());
    } catch (const std::exception& e) {
        return makeError(ErrorCode::Internal,
                         "cannot read image " + quoted(path) + ": " + e.what());
    }
}

Result<void> writeImage(const std::filesystem::path& path, const cv::Mat& image) {
    if (image.empty()) {
        return makeError(ErrorCode::InvalidArgument,
                         "cannot write an empty image to " + quoted(path));
    }
    try {
        return writeImageImpl(path, image);
    } catch (const cv::Exception& e) {
        return makeError(ErrorCode::Internal,
                         "cannot write image " + quoted(path) + ": " + e.what());
    } catch (const std::exception& e) {
        return makeError(ErrorCode::Internal,
                         "cannot write image " + quoted(path) + ": " + e.what());
    }
}

Result<void> writeTiffPage(int fd, const std::filesystem::path& name, const cv::Mat& image,
                           const TiffTags& tags) {
    const int depth = image.depth();
    if (image.empty() ||
        (depth != CV_8U && depth != CV_16U && depth != CV_32S && depth != CV_32F) ||
        image.channels() > 4) {
        return makeError(ErrorCode::Unsupported,
                         "cannot write TIFF " + quoted(name) + ": " +
                             (image.empty() ? std::string("empty image")
                                            : "type " + cv::typeToString(image.type())));
    }
    if (tags.imageDescription.find('\0') != std::string::npos) {
        return makeError(ErrorCode::InvalidArgument,
                         "cannot write TIFF " + quoted(name) + ": ImageDescription holds a NUL");
    }
    try {
        return writeTiffPageImpl(fd, name, image, tags);
    } catch (const std::exception& e) {
        return makeError(ErrorCode::Internal,
                         "cannot write TIFF " + quoted(name) + ": " + e.what());
    }
}

std::vector<cv::Size> tiffPyramidLevels(cv::Size full, int maxTopSidePx) {
    std::vector<cv::Size> levels{full};
    while (std::max(levels.back().width, levels.back().height) > std::max(maxTopSidePx, 1) &&
           levels.size() < 32) {
        const cv::Size& last = levels.back();
        levels.emplace_back((last.width + 1) / 2, (last.height + 1) / 2);
    }
    return levels;
}

Result<void> writeTiffPyramid(int fd, const std::filesystem::path& name, const cv::Mat& image,
                              const TiffTags& tags, const TiffPyramidLayout& layout) {
    if (auto ok = checkPyramidArguments(name, image, tags, layout); !ok)
        return ok;
    try {
        return writeTiffPyramidImpl(fd, name, image, tags, layout);
    } catch (const std::exception& e) {
        return makeError(ErrorCode::Internal,
                         "cannot write TIFF " + quoted(name) + ": " + e.what());
    }
}

Result<TiffPyramidInfo> readTiffPyramidInfo(const std::filesystem::path& path) {
    auto file = openLevel(path, 0);
    if (!file)
        return file.error();
    TIFF* tif = file->get();
    TiffPyramidInfo info;
    info.bigTiff = TIFFIsBigTIFF(tif) != 0;
    info.tiled = TIFFIsTiled(tif) != 0;
    const auto size = [&]() {
        std::uint32_t w = 0, h = 0;
        TIFFGetField(tif, TIFFTAG_IMAGEWIDTH, &w);
        TIFFGetField(tif, TIFFTAG_IMAGELENGTH, &h);
        return cv::Size(static_cast<int>(std::min<std::uint32_t>(w, INT32_MAX)),
                        static_cast<int>(std::min<std::uint32_t>(h, INT32_MAX)));
    };
    info.levels.push_back(size());
    if (info.tiled) {
        std::uint32_t tw = 0, th = 0;
        TIFFGetField(tif, TIFFTAG_TILEWIDTH, &tw);
        TIFFGetField(tif, TIFFTAG_TILELENGTH, &th);
        info.tileSize = cv::Size(static_cast<int>(std::min<std::uint32_t>(tw, INT32_MAX)),
                                 static_cast<int>(std::min<std::uint32_t>(th, INT32_MAX)));
    }
    std::uint16_t samples = 1, bits = 8;
    TIFFGetFieldDefaulted(tif, TIFFTAG_SAMPLESPERPIXEL, &samples);
    TIFFGetFieldDefaulted(tif, TIFFTAG_BITSPERSAMPLE, &bits);
    if ((bits == 8 || bits == 16) && samples >= 1 && samples <= 4)
        info.cvType = CV_MAKETYPE(bits == 8 ? CV_8U : CV_16U, samples);
    std::uint16_t count = 0;
    toff_t* offsets = nullptr;
    if (TIFFGetField(tif, TIFFTAG_SUBIFD, &count, &offsets) == 1 && offsets != nullptr)
        info.subIfdOffsets.assign(offsets, offsets + count);
    for (const std::uint64_t offset : info.subIfdOffsets) {
        if (TIFFSetSubDirectory(tif, offset) != 1)
            return makeError(ErrorCode::IoError, "TIFF " + quoted(path) +
                                                     ": cannot read the SubIFD at byte " +
                                                     std::to_string(offset) + file->detail());
        info.levels.push_back(size());
    }
    return info;
}

static Result<cv::Mat> readTiffTileImpl(const fs::path& path, int level, int tileX, int tileY) {
    auto file = openLevel(path, level);
    if (!file)
        return file.error();
    TIFF* tif = file->get();
    const std::string where = "TIFF " + quoted(path) + " level " + std::to_string(level);
    std::uint32_t width = 0, height = 0, tw = 0, th = 0;
    std::uint16_t samples = 1, bits = 8, format = SAMPLEFORMAT_UINT, planar = PLANARCONFIG_CONTIG;
    TIFFGetField(tif, TIFFTAG_IMAGEWIDTH, &width);
    TIFFGetField(tif, TIFFTAG_IMAGELENGTH, &height);
    TIFFGetFieldDefaulted(tif, TIFFTAG_SAMPLESPERPIXEL, &samples);
    TIFFGetFieldDefaulted(tif, TIFFTAG_BITSPERSAMPLE, &bits);
    TIFFGetFieldDefaulted(tif, TIFFTAG_SAMPLEFORMAT, &format);
    TIFFGetFieldDefaulted(tif, TIFFTAG_PLANARCONFIG, &planar);
    if (TIFFIsTiled(tif) == 0 || TIFFGetField(tif, TIFFTAG_TILEWIDTH, &tw) != 1 ||
        TIFFGetField(tif, TIFFTAG_TILELENGTH, &th) != 1 || tw == 0 || th == 0 || tw > 4096 ||
        th > 4096)
        return makeError(ErrorCode::Unsupported, where + " is not tiled in tiles of <= 4096 px");
    if ((bits != 8 && bits != 16) || (samples != 1 && samples != 3) ||
        format != SAMPLEFORMAT_UINT || planar != PLANARCONFIG_CONTIG)
        return makeError(ErrorCode::Unsupported,
                         where + ": only interleaved 8/16-bit unsigned, 1 or 3 samples");
    if (tileX < 0 || tileY < 0 || static_cast<std::uint64_t>(tileX) * tw >= width ||
        static_cast<std::uint64_t>(tileY) * th >= height)
        return makeError(ErrorCode::NotFound, where + " has no tile " + std::to_string(tileX) +
                                                  "_" + std::to_string(tileY));
    const auto x0 = static_cast<std::uint32_t>(tileX) * tw;
    const auto y0 = static_cast<std::uint32_t>(tileY) * th;
    const int type = CV_MAKETYPE(bits == 8 ? CV_8U : CV_16U, samples);
    cv::Mat block(static_cast<int>(th), static_cast<int>(tw), type);
    const auto wanted = static_cast<tmsize_t>(block.total() * block.elemSize());
    if (TIFFTileSize(tif) != wanted ||
        TIFFReadEncodedTile(tif, TIFFComputeTile(tif, x0, y0, 0, 0), block.data, wanted) != wanted)
        return makeError(ErrorCode::IoError, where + ": cannot decode tile " +
                                                 std::to_string(tileX) + "_" +
                                                 std::to_string(tileY) + file->detail());
    cv::Mat out = block(cv::Rect(0, 0, static_cast<int>(std::min(tw, width - x0)),
                                 static_cast<int>(std::min(th, height - y0))))
                      .clone();
    if (samples == 3)
        cv::cvtColor(out, out, cv::COLOR_RGB2BGR);
    return out;
}

Result<cv::Mat> readTiffTile(const std::filesystem::path& path, int level, int tileX, int tileY) {
    try {
        return readTiffTileImpl(path, level, tileX, tileY);
    } catch (const std::exception& e) {
        return makeError(ErrorCode::Internal,
                         "cannot read a tile of TIFF " + quoted(path) + ": " + e.what());
    }
}

Result<std::optional<std::string>> readTiffDescription(const std::filesystem::path& path) {
    std::error_code ec;
    if (!fs::exists(path, ec)) {
        return makeError(ErrorCode::NotFound, "TIFF " + quoted(path) + " does not exist");
    }
    auto file = TiffFile::open(path, "r");
    if (!file) {
        return makeError(ErrorCode::IoError, "not a readable TIFF: " + file.error().message,
                         file.error().sysErrno);
    }
    const char* description = nullptr;
    if (TIFFGetField(file->get(), TIFFTAG_IMAGEDESCRIPTION, &description) != 1 ||
        description == nullptr) {
        return std::optional<std::string>();
    }
    return std::optional<std::string>(description);
}

void setTiffWriteFaultForTesting(int err) noexcept {
    gWriteFault.store(err);
}

std::optional<cv::Size> jpegFrameSize(const std::uint8_t* data, std::size_t size) {
    const auto header = data == nullptr ? std::nullopt : jpegHeader(data, size);
    if (!header) {
        return std::nullopt;
    }
    return cv::Size(static_cast<int>(header->width), static_cast<int>(header->height));
}

} // namespace slicestation::core
