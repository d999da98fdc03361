// PNG and JPEG through libpng and libjpeg-turbo (core/codec.hpp), checked against OpenCV's own
// codecs (which the product no longer loads) as the reference reader and writer.
#include "slicestation/core/codec.hpp"

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <png.h>
#include <turbojpeg.h>
#include <zlib.h>

#include <cstdint>
#include <vector>

namespace slicestation::core {
namespace {

cv::Mat noise(int rows, int cols, int type, unsigned seed) {
    cv::Mat m(rows, cols, type);
    cv::RNG rng(seed);
    rng.fill(m, cv::RNG::UNIFORM, 0, m.depth() == CV_16U ? 65536 : 256);
    return m;
}

double maxDifference(const cv::Mat& a, const cv::Mat& b) {
    if (a.size() != b.size() || a.type() != b.type()) {
        return 1e9;
    }
    return cv::norm(a, b, cv::NORM_INF);
}

std::vector<std::uint8_t> opencvEncode(const char* ext, const cv::Mat& m,
                                       const std::vector<int>& params = {}) {
    std::vector<std::uint8_t> bytes;
    EXPECT_TRUE(cv::imencode(ext, m, bytes, params));
    return bytes;
}

TEST(Codec, PngRoundTripsEveryDepthAndChannelCountItWrites) {
    for (const int type : {CV_8UC1, CV_8UC3, CV_8UC4, CV_16UC1, CV_16UC3, CV_16UC4}) {
        const cv::Mat image = noise(37, 53, type, static_cast<unsigned>(type) + 1);
        auto bytes = encodePng(image);
        ASSERT_TRUE(bytes.ok()) << bytes.error().message;
        auto back = decodePng(*bytes, "round trip");
        ASSERT_TRUE(back.ok()) << back.error().message;
        EXPECT_EQ(back->type(), type) << cv::typeToString(type);
        EXPECT_EQ(maxDifference(*back, image), 0) << cv::typeToString(type);
        // OpenCV reads what we write as we do (byte order, BGR order).
        const cv::Mat opencv = cv::imdecode(*bytes, cv::IMREAD_UNCHANGED);
        EXPECT_EQ(maxDifference(opencv, image), 0) << cv::typeToString(type);
    }
}

TEST(Codec, PngReadsWhatOpenCvWritesAsOpenCvReadsIt) {
    for (const int type : {CV_8UC1, CV_8UC3, CV_8UC4, CV_16UC1, CV_16UC3}) {
        const cv::Mat image = noise(64, 48, type, 7);
        const auto bytes = opencvEncode(".png", image, {cv::IMWRITE_PNG_COMPRESSION, 9});
        auto ours = decodePng(bytes, "opencv's png");
        ASSERT_TRUE(ours.ok()) << ours.error().message;
        EXPECT_EQ(maxDifference(*ours, cv::imdecode(bytes, cv::IMREAD_UNCHANGED)), 0)
            << cv::typeToString(type);
    }
    // Bilevel (1-bit grey) is expanded to 0 / 255, as OpenCV does.
    cv::Mat bilevel(16, 24, CV_8UC1);
    for (int y = 0; y < bilevel.rows; ++y) {
        for (int x = 0; x < bilevel.cols; ++x) {
            bilevel.at<std::uint8_t>(y, x) = (x + y) % 3 == 0 ? 255 : 0;
        }
    }
    const auto bytes = opencvEncode(".png", bilevel, {cv::IMWRITE_PNG_BILEVEL, 1});
    auto ours = decodePng(bytes, "bilevel");
    ASSERT_TRUE(ours.ok()) << ours.error().message;
    EXPECT_EQ(maxDifference(*ours, bilevel), 0);
}

TEST(Codec, PngPaletteBecomesBgrAndGreyAlphaKeepsTwoChannels) {
    // A palette PNG written by libpng's simplified API (colour-mapped RGB).
    const int w = 20, h = 10;
    std::vector<std::uint8_t> indices(static_cast<std::size_t>(w * h));
    for (std::size_t i = 0; i < indices.size(); ++i) {
        indices[i] = static_cast<std::uint8_t>(i % 3);
    }
    const std::uint8_t colourMap[9] = {255, 0, 0, 0, 128, 0, 10, 20, 30}; // RGB entries
    png_image pi{};
    pi.version = PNG_IMAGE_VERSION;
    pi.width = w;
    pi.height = h;
    pi.format = PNG_FORMAT_RGB_COLORMAP;
    pi.colormap_entries = 3;
    png_alloc_size_t size = 0;
    ASSERT_TRUE(png_image_write_get_memory_size(pi, size, 0, indices.data(), 0, colourMap));
    std::vector<std::uint8_t> bytes(size);
    ASSERT_TRUE(
        png_image_write_to_memory(&pi, bytes.data(), &size, 0, indices.data(), 0, colourMap))
        << pi.message;
    bytes.resize(size);
    auto palette = decodePng(bytes, "palette");
    ASSERT_TRUE(palette.ok()) << palette.error().message;
    ASSERT_EQ(palette->type(), CV_8UC3);
    EXPECT_EQ(palette->at<cv::Vec3b>(0, 0), cv::Vec3b(0, 0, 255)); // red, in BGR
    EXPECT_EQ(palette->at<cv::Vec3b>(0, 1), cv::Vec3b(0, 128, 0));
    EXPECT_EQ(palette->at<cv::Vec3b>(0, 2), cv::Vec3b(30, 20, 10));

    // Grey + alpha, 8 bit.
    std::vector<std::uint8_t> ga(static_cast<std::size_t>(w * h * 2));
    for (std::size_t i = 0; i < ga.size(); ++i) {
        ga[i] = static_cast<std::uint8_t>(i * 7);
    }
    png_image gi{};
    gi.version = PNG_IMAGE_VERSION;
    gi.width = w;
    gi.height = h;
    gi.format = PNG_FORMAT_GA;
    size = 0;
    ASSERT_TRUE(png_image_write_get_memory_size(gi, size, 0, ga.data(), 0, nullptr));
    bytes.assign(size, 0);
    ASSERT_TRUE(png_image_write_to_memory(&gi, bytes.data(), &size, 0, ga.data(), 0, nullptr))
        << gi.message;
    bytes.resize(size);
    auto greyAlpha = decodePng(bytes, "grey alpha");
    ASSERT_TRUE(greyAlpha.ok()) << greyAlpha.error().message;
    ASSERT_EQ(greyAlpha->type(), CV_8UC2);
    EXPECT_EQ(std::vector<std::uint8_t>(greyAlpha->datastart, greyAlpha->dataend), ga);
}

/// The PNG chunk at `at` (length, type, data, CRC) gets a fresh CRC after an edit.
void fixCrc(std::vector<std::uint8_t>& png, std::size_t at) {
    const std::size_t length = (std::size_t{png[at]} << 24) | (std::size_t{png[at + 1]} << 16) |
                               (std::size_t{png[at + 2]} << 8) | png[at + 3];
    const uLong crc = crc32(0, png.data() + at + 4, static_cast<uInt>(length + 4));
    for (int k = 0; k < 4; ++k) {
        png[at + 8 + length + static_cast<std::size_t>(k)] =
            static_cast<std::uint8_t>(crc >> (24 - 8 * k));
    }
}

TEST(Codec, CorruptTruncatedOrHugePngsAreErrorsNamingTheData) {
    const auto good = *encodePng(noise(40, 40, CV_8UC3, 3));
    // Not a PNG.
    auto read = decodePng(std::vector<std::uint8_t>{'G', 'I', 'F', '8', '9', 'a', 0, 0}, "x.gif");
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::IoError);
    EXPECT_NE(read.error().message.find("x.gif"), std::string::npos) << read.error().message;
    // Truncated in the pixel data, at every tenth byte.
    for (std::size_t cut = 8; cut < good.size() - 12; cut += good.size() / 10) {
        read = decodePng(std::span(good.data(), cut), "cut.png");
        ASSERT_FALSE(read.ok()) << cut;
        EXPECT_EQ(read.error().code, ErrorCode::IoError) << cut;
    }
    // A flipped bit in the image data: the CRC of the critical chunk fails.
    auto flipped = good;
    flipped[good.size() / 2] ^= 0x10;
    read = decodePng(flipped, "flipped.png");
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::IoError);
    EXPECT_NE(read.error().message.find("flipped.png"), std::string::npos);
    // The header claims 40000 x 40000 RGB (4.8 GB): refused before anything is allocated.
    auto huge = good;
    for (const std::size_t at : {std::size_t{16}, std::size_t{20}}) {
        huge[at] = 0;
        huge[at + 1] = 0;
        huge[at + 2] = 40000 >> 8;
        huge[at + 3] = 40000 & 0xFF;
    }
    fixCrc(huge, 8);
    read = decodePng(huge, "huge.png");
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::Unsupported) << read.error().message;
}

TEST(Codec, JpegDecodesAsOpenCvDoesInEveryPixelMode) {
    const cv::Mat colour = noise(48, 64, CV_8UC3, 11);
    cv::Mat smooth;
    cv::GaussianBlur(colour, smooth, cv::Size(7, 7), 2);
    for (const int quality : {50, 95}) {
        const auto bytes = opencvEncode(".jpg", smooth, {cv::IMWRITE_JPEG_QUALITY, quality});
        auto bgr = decodeJpeg(bytes, JpegPixels::AsStored, "colour.jpg");
        ASSERT_TRUE(bgr.ok()) << bgr.error().message;
        EXPECT_LE(maxDifference(*bgr, cv::imdecode(bytes, cv::IMREAD_COLOR)), 1) << quality;
        auto rgb = decodeJpeg(bytes, JpegPixels::Rgb, "colour.jpg");
        ASSERT_TRUE(rgb.ok());
        cv::Mat swapped;
        cv::cvtColor(*rgb, swapped, cv::COLOR_RGB2BGR);
        EXPECT_EQ(maxDifference(swapped, *bgr), 0);
        auto grey = decodeJpeg(bytes, JpegPixels::Grey, "colour.jpg");
        ASSERT_TRUE(grey.ok());
        EXPECT_LE(maxDifference(*grey, cv::imdecode(bytes, cv::IMREAD_GRAYSCALE)), 1) << quality;
    }
    // A grey JPEG stays one channel as stored, and becomes three when BGR is asked.
    cv::Mat greySource;
    cv::cvtColor(smooth, greySource, cv::COLOR_BGR2GRAY);
    const auto bytes = opencvEncode(".jpg", greySource);
    auto grey = decodeJpeg(bytes, JpegPixels::AsStored, "grey.jpg");
    ASSERT_TRUE(grey.ok());
    EXPECT_EQ(grey->type(), CV_8UC1);
    EXPECT_LE(maxDifference(*grey, cv::imdecode(bytes, cv::IMREAD_UNCHANGED)), 1);
    auto three = decodeJpeg(bytes, JpegPixels::Bgr, "grey.jpg");
    ASSERT_TRUE(three.ok());
    EXPECT_EQ(three->type(), CV_8UC3);
}

TEST(Codec, JpegEncodesWhatOpenCvReadsAndRefusesWhatItCannot) {
    cv::Mat smooth;
    cv::GaussianBlur(noise(40, 56, CV_8UC3, 5), smooth, cv::Size(9, 9), 3);
    for (const int channels : {1, 3}) {
        cv::Mat image = smooth;
        if (channels == 1) {
            cv::cvtColor(smooth, image, cv::COLOR_BGR2GRAY);
        }
        auto bytes = encodeJpeg(image, 95);
        ASSERT_TRUE(bytes.ok()) << bytes.error().message;
        const cv::Mat back = cv::imdecode(*bytes, cv::IMREAD_UNCHANGED);
        ASSERT_EQ(back.type(), image.type());
        EXPECT_GT(cv::PSNR(back, image), 35) << channels;
    }
    for (const auto& [image, quality] :
         {std::pair{cv::Mat(), 90}, std::pair{cv::Mat(8, 8, CV_16UC1, cv::Scalar(1)), 90},
          std::pair{cv::Mat(8, 8, CV_8UC4, cv::Scalar(1)), 90},
          std::pair{cv::Mat(8, 8, CV_8UC1, cv::Scalar(1)), 0}}) {
        auto bytes = encodeJpeg(image, quality);
        ASSERT_FALSE(bytes.ok());
        EXPECT_EQ(bytes.error().code, ErrorCode::InvalidArgument);
    }
    auto png = encodePng(cv::Mat(8, 8, CV_32FC1, cv::Scalar(1)));
    ASSERT_FALSE(png.ok());
    EXPECT_EQ(png.error().code, ErrorCode::InvalidArgument);
}

TEST(Codec, CorruptOrTruncatedJpegsAreErrorsNotHalfImages) {
    cv::Mat smooth;
    cv::GaussianBlur(noise(64, 64, CV_8UC3, 9), smooth, cv::Size(5, 5), 1);
    const auto good = opencvEncode(".jpg", smooth);
    ASSERT_TRUE(decodeJpeg(good, JpegPixels::AsStored, "good.jpg").ok());
    // OpenCV returns a half-grey image for a truncated stream; we refuse it.
    const std::span half(good.data(), good.size() / 2);
    ASSERT_FALSE(cv::imdecode(std::vector<std::uint8_t>(half.begin(), half.end()), cv::IMREAD_COLOR)
                     .empty());
    auto read = decodeJpeg(half, JpegPixels::AsStored, "half.jpg");
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::IoError);
    EXPECT_NE(read.error().message.find("half.jpg"), std::string::npos) << read.error().message;
    // A CMYK JPEG (as print workflows write them) is refused by name, not as corrupt.
    const cv::Mat ink(16, 16, CV_8UC4, cv::Scalar(10, 200, 30, 0));
    tjhandle tj = tjInitCompress();
    ASSERT_NE(tj, nullptr);
    unsigned char* cmyk = nullptr;
    unsigned long cmykSize = 0;
    ASSERT_EQ(tjCompress2(tj, ink.data, 16, 0, 16, TJPF_CMYK, &cmyk, &cmykSize, TJSAMP_444, 90, 0),
              0)
        << tjGetErrorStr2(tj);
    read = decodeJpeg(std::span(cmyk, cmykSize), JpegPixels::AsStored, "ink.jpg");
    tjFree(cmyk);
    tjDestroy(tj);
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::Unsupported);
    EXPECT_NE(read.error().message.find("CMYK"), std::string::npos) << read.error().message;
    // Not a JPEG at all, or nothing.
    for (const auto& bytes : {std::vector<std::uint8_t>{}, std::vector<std::uint8_t>(100, 0x42)}) {
        read = decodeJpeg(bytes, JpegPixels::AsStored, "garbage.jpg");
        ASSERT_FALSE(read.ok());
        EXPECT_EQ(read.error().code, ErrorCode::IoError);
    }
}

} // namespace
} // namespace slicestation::core
