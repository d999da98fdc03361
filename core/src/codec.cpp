#include "slicestation/core/codec.hpp"

#include "image_limits.hpp"

#include <png.h>
#include <turbojpeg.h>

#include <csetjmp>
#include <cstdio>
#include <cstring>
#include <memory>
#include <optional>
#include <string>

namespace slicestation::core {
namespace {

/// A header claiming no pixels at all is corrupt; one claiming too many is beyond the limits.
Result<void> checkDecodedSize(const std::string& what, std::uint64_t width, std::uint64_t height,
                              int channels, int sampleBytes) {
    if (width == 0 || height == 0) {
        return makeError(ErrorCode::IoError, what + ": the header claims an empty image");
    }
    return checkImageSize(what, width, height, channels, sampleBytes);
}

// ---------------------------------------------------------------------------------------------
// PNG (libpng reports errors by longjmp: the functions holding a setjmp have only trivial
// locals and write what they produce through pointers into their callers' objects)

struct PngJob {
    const std::uint8_t* data = nullptr;
    std::size_t size = 0;
    std::size_t at = 0;
    char message[256] = {};
    // decoding
    const std::string* what = nullptr; ///< names the data in messages
    cv::Mat* image = nullptr;
    std::vector<png_bytep>* rows = nullptr;
    std::optional<Error> sizeError; ///< the decoded image would exceed the limits
    // encoding
    const cv::Mat* source = nullptr;
    std::vector<std::uint8_t>* out = nullptr;
};

[[noreturn]] void pngFail(png_structp png, png_const_charp message) {
    auto* job = static_cast<PngJob*>(png_get_error_ptr(png));
    std::snprintf(job->message, sizeof job->message, "%s", message);
    png_longjmp(png, 1);
}

void pngQuiet(png_structp /*png*/, png_const_charp /*message*/) {}

void pngReadBytes(png_structp png, png_bytep out, png_size_t count) {
    auto* job = static_cast<PngJob*>(png_get_io_ptr(png));
    if (count > job->size - job->at) {
        png_error(png, "the file ends early (truncated)");
    }
    std::memcpy(out, job->data + job->at, count);
    job->at += count;
}

void pngWriteBytes(png_structp png, png_bytep in, png_size_t count) {
    auto* job = static_cast<PngJob*>(png_get_io_ptr(png));
    bool failed = false;
    try {
        job->out->insert(job->out->end(), in, in + count);
    } catch (...) {
        failed = true;
    }
    if (failed) {
        png_error(png, "out of memory");
    }
}

void pngFlush(png_structp /*png*/) {}

/// Allocates the decoded image once the header is known (outside the setjmp frame's locals).
bool pngAllocate(PngJob& job, int width, int height, int channels, int bitDepth) {
    const int sampleBytes = bitDepth > 8 ? 2 : 1;
    if (auto fits = checkDecodedSize(*job.what, static_cast<std::uint64_t>(width),
                                     static_cast<std::uint64_t>(height), channels, sampleBytes);
        !fits) {
        job.sizeError = fits.error();
        return false;
    }
    job.image->create(height, width, CV_MAKETYPE(sampleBytes == 2 ? CV_16U : CV_8U, channels));
    job.rows->resize(static_cast<std::size_t>(height));
    for (int y = 0; y < height; ++y) {
        (*job.rows)[static_cast<std::size_t>(y)] = job.image->ptr<png_byte>(y);
    }
    return true;
}

bool pngDecodeInto(png_structp png, png_infop info, PngJob* job) {
    if (setjmp(png_jmpbuf(png))) {
        return false;
    }
    png_set_read_fn(png, job, pngReadBytes);
    png_set_user_limits(png, 0x7fffffff, 0x7fffffff);
    png_set_chunk_malloc_max(png, 8u << 20); // text, ICC profiles: at most 8 MiB each
    png_read_info(png, info);
    const int colourType = png_get_color_type(png, info);
    const int bitDepth = png_get_bit_depth(png, info);
    if (colourType == PNG_COLOR_TYPE_PALETTE) {
        png_set_palette_to_rgb(png);
    }
    if (colourType == PNG_COLOR_TYPE_GRAY && bitDepth < 8) {
        png_set_expand_gray_1_2_4_to_8(png);
    }
    if (bitDepth == 16) {
        png_set_swap(png); // PNG is big-endian, cv::Mat native (little-endian here)
    }
    if ((colourType & PNG_COLOR_MASK_COLOR) != 0) {
        png_set_bgr(png);
    }
    png_set_interlace_handling(png);
    png_read_update_info(png, info);
    const auto width = static_cast<int>(png_get_image_width(png, info));
    const auto height = static_cast<int>(png_get_image_height(png, info));
    if (!pngAllocate(*job, width, height, png_get_channels(png, info),
                     png_get_bit_depth(png, info))) {
        return false;
    }
    png_read_image(png, job->rows->data());
    png_read_end(png, nullptr);
    return true;
}

bool pngEncodeInto(png_structp png, png_infop info, PngJob* job) {
    if (setjmp(png_jmpbuf(png))) {
        return false;
    }
    const cv::Mat& m = *job->source;
    png_set_write_fn(png, job, pngWriteBytes, pngFlush);
    const int channels = m.channels();
    const int colourType = channels == 1   ? PNG_COLOR_TYPE_GRAY
                           : channels == 3 ? PNG_COLOR_TYPE_RGB
                                           : PNG_COLOR_TYPE_RGB_ALPHA;
    png_set_IHDR(png, info, static_cast<png_uint_32>(m.cols), static_cast<png_uint_32>(m.rows),
                 m.depth() == CV_16U ? 16 : 8, colourType, PNG_INTERLACE_NONE,
                 PNG_COMPRESSION_TYPE_DEFAULT, PNG_FILTER_TYPE_DEFAULT);
    png_set_filter(png, PNG_FILTER_TYPE_BASE, PNG_FILTER_SUB);
    png_set_compression_level(png, 1);
    png_set_compression_strategy(png, 3); // Z_RLE
    png_write_info(png, info);
    if (m.depth() == CV_16U) {
        png_set_swap(png);
    }
    if (channels >= 3) {
        png_set_bgr(png);
    }
    for (int y = 0; y < m.rows; ++y) {
        png_write_row(png, m.ptr<png_byte>(y));
    }
    png_write_end(png, nullptr);
    return true;
}

// ---------------------------------------------------------------------------------------------
// JPEG (the TurboJPEG API reports errors by return value)

struct TjDeleter {
    void operator()(void* handle) const noexcept { tjDestroy(handle); }
};
using TjHandle = std::unique_ptr<void, TjDeleter>;

std::string tjReason(void* handle) {
    return tjGetErrorStr2(handle);
}

} // namespace

Result<cv::Mat> decodePng(std::span<const std::uint8_t> data, std::string_view what) {
    if (data.size() < 8 || png_sig_cmp(data.data(), 0, 8) != 0) {
        return makeError(ErrorCode::IoError, std::string(what) + ": not a PNG (no signature)");
    }
    cv::Mat image;
    std::vector<png_bytep> rows;
    const std::string name(what);
    PngJob job;
    job.what = &name;
    job.data = data.data();
    job.size = data.size();
    job.image = &image;
    job.rows = &rows;
    png_structp png = png_create_read_struct(PNG_LIBPNG_VER_STRING, &job, pngFail, pngQuiet);
    png_infop info = png ? png_create_info_struct(png) : nullptr;
    if (!info) {
        png_destroy_read_struct(&png, nullptr, nullptr);
        return makeError(ErrorCode::Internal, std::string(what) + ": libpng could not start");
    }
    const bool ok = pngDecodeInto(png, info, &job);
    png_destroy_read_struct(&png, &info, nullptr);
    if (job.sizeError) {
        return *job.sizeError;
    }
    if (!ok) {
        return makeError(ErrorCode::IoError,
                         std::string(what) + ": corrupt or truncated PNG (" + job.message + ")");
    }
    return image;
}

Result<std::vector<std::uint8_t>> encodePng(const cv::Mat& image) {
    const int depth = image.depth();
    const int channels = image.channels();
    if (image.empty() || (depth != CV_8U && depth != CV_16U) ||
        (channels != 1 && channels != 3 && channels != 4)) {
        return makeError(ErrorCode::InvalidArgument,
                         "PNG takes 8/16-bit images with 1, 3 or 4 channels, not " +
                             cv::typeToString(image.type()) + (image.empty() ? " (empty)" : ""));
    }
    std::vector<std::uint8_t> out;
    PngJob job;
    job.source = &image;
    job.out = &out;
    png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, &job, pngFail, pngQuiet);
    png_infop info = png ? png_create_info_struct(png) : nullptr;
    if (!info) {
        png_destroy_write_struct(&png, nullptr);
        return makeError(ErrorCode::Internal, "libpng could not start");
    }
    const bool ok = pngEncodeInto(png, info, &job);
    png_destroy_write_struct(&png, &info);
    if (!ok) {
        return makeError(ErrorCode::Internal, std::string("libpng: ") + job.message);
    }
    return out;
}

Result<cv::Mat> decodeJpeg(std::span<const std::uint8_t> data, JpegPixels pixels,
                           std::string_view what) {
    const TjHandle tj(tjInitDecompress());
    if (!tj) {
        return makeError(ErrorCode::Internal,
                         std::string(what) + ": libjpeg-turbo could not start");
    }
    if (data.empty()) {
        return makeError(ErrorCode::IoError, std::string(what) + ": empty JPEG");
    }
    int width = 0, height = 0, subsampling = 0, colourSpace = 0;
    if (tjDecompressHeader3(tj.get(), data.data(), static_cast<unsigned long>(data.size()), &width,
                            &height, &subsampling, &colourSpace) != 0) {
        return makeError(ErrorCode::IoError, std::string(what) +
                                                 ": not a JPEG or a corrupt header (" +
                                                 tjReason(tj.get()) + ")");
    }
    if (colourSpace == TJCS_CMYK || colourSpace == TJCS_YCCK) {
        // Print workflows write these; no camera or slide scanner does, and turning ink
        // coverage into light needs a colour profile.
        return makeError(ErrorCode::Unsupported,
                         std::string(what) + ": a CMYK JPEG, which is not read (save it as RGB)");
    }
    const bool grey =
        pixels == JpegPixels::Grey || (pixels == JpegPixels::AsStored && colourSpace == TJCS_GRAY);
    if (auto fits = checkDecodedSize(std::string(what), static_cast<std::uint64_t>(width),
                                     static_cast<std::uint64_t>(height), grey ? 1 : 3, 1);
        !fits) {
        return fits.error();
    }
    cv::Mat image(height, width, grey ? CV_8UC1 : CV_8UC3);
    const int format = grey ? TJPF_GRAY : pixels == JpegPixels::Rgb ? TJPF_RGB : TJPF_BGR;
    if (tjDecompress2(tj.get(), data.data(), static_cast<unsigned long>(data.size()), image.data,
                      width, static_cast<int>(image.step), height, format,
                      TJFLAG_STOPONWARNING | TJFLAG_LIMITSCANS) != 0) {
        return makeError(ErrorCode::IoError, std::string(what) + ": corrupt or truncated JPEG (" +
                                                 tjReason(tj.get()) + ")");
    }
    return image;
}

Result<std::vector<std::uint8_t>> encodeJpeg(const cv::Mat& image, int quality) {
    if (image.empty() || image.depth() != CV_8U ||
        (image.channels() != 1 && image.channels() != 3) || quality < 1 || quality > 100) {
        return makeError(ErrorCode::InvalidArgument,
                         "JPEG takes 8-bit images with 1 or 3 channels and a quality of 1..100, "
                         "not " +
                             cv::typeToString(image.type()) + " at " + std::to_string(quality));
    }
    const TjHandle tj(tjInitCompress());
    if (!tj) {
        return makeError(ErrorCode::Internal, "libjpeg-turbo could not start");
    }
    const bool grey = image.channels() == 1;
    unsigned char* buffer = nullptr;
    unsigned long size = 0;
    const int rc = tjCompress2(tj.get(), image.data, image.cols, static_cast<int>(image.step),
                               image.rows, grey ? TJPF_GRAY : TJPF_BGR, &buffer, &size,
                               grey ? TJSAMP_GRAY : TJSAMP_420, quality, 0);
    const std::unique_ptr<unsigned char, decltype(&tjFree)> owned(buffer, &tjFree);
    if (rc != 0) {
        return makeError(ErrorCode::Internal, "libjpeg-turbo: " + tjReason(tj.get()));
    }
    return std::vector<std::uint8_t>(buffer, buffer + size);
}

} // namespace slicestation::core
