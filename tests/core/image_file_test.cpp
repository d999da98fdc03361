#include "slicestation/core/image_file.hpp"

#include "../common/jpeg_bytes.hpp"
#include "../common/test_dir.hpp"

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <zlib.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <limits>
#include <random>
#include <string>
#include <vector>

namespace slicestation::core {
namespace {

namespace fs = std::filesystem;

/// A fresh directory under the system temp directory, removed afterwards.
class ImageFileTest : public testing_dir::TempDirTest {
protected:
    ImageFileTest() : TempDirTest("image-file") {}

    fs::path file(const std::string& name) const { return dir_ / name; }

    void writeBytes(const fs::path& path, const std::vector<std::uint8_t>& bytes) const {
        std::ofstream out(path, std::ios::binary);
        out.write(reinterpret_cast<const char*>(bytes.data()),
                  static_cast<std::streamsize>(bytes.size()));
        ASSERT_TRUE(out.good()) << path;
    }

    std::vector<std::uint8_t> readBytes(const fs::path& path) const {
        std::ifstream in(path, std::ios::binary);
        return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
    }

    std::vector<std::string> entries() const {
        std::vector<std::string> names;
        for (const auto& entry : fs::directory_iterator(dir_)) {
            names.push_back(entry.path().filename().string());
        }
        std::sort(names.begin(), names.end());
        return names;
    }
};

/// Deterministic test pattern covering the whole value range of the depth.
cv::Mat pattern(int depth, int channels, int rows = 37, int cols = 53) {
    cv::Mat image(rows, cols, CV_MAKETYPE(depth, channels));
    cv::RNG rng(12345 + depth * 10 + channels);
    switch (depth) {
    case CV_8U:
        rng.fill(image, cv::RNG::UNIFORM, 0, 256);
        break;
    case CV_16U:
        rng.fill(image, cv::RNG::UNIFORM, 0, 65536);
        break;
    case CV_32S:
        rng.fill(image, cv::RNG::UNIFORM, 0, 2147483647.0);
        break;
    default:
        rng.fill(image, cv::RNG::UNIFORM, -1.0e6, 1.0e6);
        break;
    }
    return image;
}

bool identical(const cv::Mat& a, const cv::Mat& b) {
    return a.type() == b.type() && a.size() == b.size() &&
           cv::norm(a.reshape(1), b.reshape(1), cv::NORM_INF) == 0.0;
}

// ----------------------------------------------------------------------------------------------
// Round trips

struct RoundTripCase {
    std::string extension;
    int depth;
    int channels;
};

std::string caseName(const ::testing::TestParamInfo<RoundTripCase>& info) {
    const char* depthName = info.param.depth == CV_8U    ? "8U"
                            : info.param.depth == CV_16U ? "16U"
                            : info.param.depth == CV_32S ? "32S"
                                                         : "32F";
    return info.param.extension.substr(1) + "_" + depthName + "C" +
           std::to_string(info.param.channels);
}

std::vector<RoundTripCase> roundTripCases() {
    std::vector<RoundTripCase> cases;
    for (int depth : {CV_8U, CV_16U}) {
        for (int channels : {1, 3, 4}) {
            cases.push_back({".png", depth, channels});
        }
    }
    for (int depth : {CV_8U, CV_16U, CV_32S, CV_32F}) {
        for (int channels : {1, 2, 3, 4}) {
            cases.push_back({".tif", depth, channels});
        }
    }
    return cases;
}

class ImageRoundTrip : public ImageFileTest, public ::testing::WithParamInterface<RoundTripCase> {};

TEST_P(ImageRoundTrip, ReadsBackExactlyWhatWasWritten) {
    const auto& param = GetParam();
    const cv::Mat image = pattern(param.depth, param.channels);
    const fs::path path = file("image" + param.extension);
    const Result<void> written = writeImage(path, image);
    ASSERT_TRUE(written.ok()) << written.error().message;
    const Result<cv::Mat> read = readImage(path);
    ASSERT_TRUE(read.ok()) << read.error().message;
    EXPECT_EQ(read->type(), image.type());
    EXPECT_TRUE(identical(*read, image));
    // Only the final file is left: the temporary one was renamed.
    EXPECT_EQ(entries(), std::vector<std::string>{path.filename().string()});
}

INSTANTIATE_TEST_SUITE_P(AllFormats, ImageRoundTrip, ::testing::ValuesIn(roundTripCases()),
                         caseName);

TEST_F(ImageFileTest, WrittenColourTiffMatchesOpenCvsOwnReader) {
    // OpenCV reads TIFF independently of us: the channel order on disk must be RGB.
    cv::Mat image(4, 6, CV_8UC3, cv::Scalar(255, 20, 0)); // blue in BGR
    image.at<cv::Vec3b>(1, 2) = cv::Vec3b(0, 0, 250);     // one red pixel
    ASSERT_TRUE(writeImage(file("colour.tif"), image).ok());
    const cv::Mat opencv = cv::imread(file("colour.tif").string(), cv::IMREAD_UNCHANGED);
    EXPECT_TRUE(identical(opencv, image));
}

TEST_F(ImageFileTest, WritesRegionsOfLargerImagesAndUpperCaseExtensions) {
    const cv::Mat big = pattern(CV_16U, 1, 40, 60);
    const cv::Mat roi = big(cv::Rect(5, 7, 31, 17)); // not continuous in memory
    ASSERT_TRUE(writeImage(file("roi.TIF"), roi).ok());
    ASSERT_TRUE(writeImage(file("roi.PNG"), roi).ok());
    for (const char* name : {"roi.TIF", "roi.PNG"}) {
        const Result<cv::Mat> read = readImage(file(name));
        ASSERT_TRUE(read.ok()) << read.error().message;
        EXPECT_TRUE(identical(*read, roi)) << name;
    }
}

TEST_F(ImageFileTest, OverwritesAnExistingFileWholly) {
    const fs::path path = file("label.tif");
    ASSERT_TRUE(writeImage(path, pattern(CV_32F, 1, 300, 300)).ok());
    const cv::Mat small = pattern(CV_8U, 1, 3, 4);
    ASSERT_TRUE(writeImage(path, small).ok());
    const Result<cv::Mat> read = readImage(path);
    ASSERT_TRUE(read.ok()) << read.error().message;
    EXPECT_TRUE(identical(*read, small));
    EXPECT_EQ(entries(), std::vector<std::string>{"label.tif"});
}

TEST_F(ImageFileTest, ReadsByContentNotByExtension) {
    const cv::Mat image = pattern(CV_16U, 1);
    ASSERT_TRUE(writeImage(file("really_tiff.tif"), image).ok());
    fs::rename(file("really_tiff.tif"), file("misnamed.png"));
    const Result<cv::Mat> read = readImage(file("misnamed.png"));
    ASSERT_TRUE(read.ok()) << read.error().message;
    EXPECT_TRUE(identical(*read, image));
}

// ----------------------------------------------------------------------------------------------
// Hand-made TIFF files, independent of our writer

enum : std::uint16_t {
    kAscii = 2,
    kShort = 3,
    kLong = 4,
    kWidth = 256,
    kLength = 257,
    kBits = 258,
    kCompression = 259,
    kPhotometric = 262,
    kDescription = 270,
    kStripOffsets = 273,
    kSamples = 277,
    kRowsPerStrip = 278,
    kStripByteCounts = 279,
    kPlanar = 284,
    kTileWidth = 322,
    kTileLength = 323,
    kTileOffsets = 324,
    kTileByteCounts = 325,
    kSampleFormat = 339,
};

struct TiffEntry {
    std::uint16_t tag;
    std::uint16_t type;
    std::vector<std::uint32_t> values;
};

struct TiffPage {
    std::vector<TiffEntry> entries; ///< without offsets/byte counts: those come from `blocks`
    std::vector<std::vector<std::uint8_t>> blocks; ///< strips or tiles, in file order
    bool tiled = false;
};

std::size_t valueSize(std::uint16_t type) {
    return type == kAscii ? 1 : type == kShort ? 2 : 4;
}

/// Serialises baseline TIFF pages: per page the IFD, its out-of-line values, then its blocks.
class TiffBytes {
public:
    explicit TiffBytes(bool bigEndian) : big_(bigEndian) {}

    std::vector<std::uint8_t> build(std::vector<TiffPage> pages) {
        bytes_.clear();
        bytes_.push_back(big_ ? 'M' : 'I');
        bytes_.push_back(big_ ? 'M' : 'I');
        put16(42);
        put32(8);
        for (std::size_t p = 0; p < pages.size(); ++p) {
            TiffPage& page = pages[p];
            std::vector<std::uint32_t> counts;
            for (const auto& block : page.blocks) {
                counts.push_back(static_cast<std::uint32_t>(block.size()));
            }
            const std::uint16_t offsetsTag = page.tiled ? kTileOffsets : kStripOffsets;
            const std::uint16_t countsTag = page.tiled ? kTileByteCounts : kStripByteCounts;
            page.entries.push_back({offsetsTag, kLong, std::vector<std::uint32_t>(counts.size())});
            page.entries.push_back({countsTag, kLong, counts});
            std::sort(page.entries.begin(), page.entries.end(),
                      [](const TiffEntry& a, const TiffEntry& b) { return a.tag < b.tag; });

            const std::size_t ifdStart = bytes_.size();
            const std::size_t ifdSize = 2 + 12 * page.entries.size() + 4;
            std::size_t extraSize = 0;
            for (const auto& entry : page.entries) {
                const std::size_t size = entry.values.size() * valueSize(entry.type);
                extraSize += size > 4 ? size : 0;
            }
            std::size_t dataStart = ifdStart + ifdSize + extraSize;
            std::size_t blocksSize = 0;
            for (auto& entry : page.entries) {
                if (entry.tag == offsetsTag) {
                    for (std::size_t b = 0; b < page.blocks.size(); ++b) {
                        entry.values[b] = static_cast<std::uint32_t>(dataStart + blocksSize);
                        blocksSize += page.blocks[b].size();
                    }
                }
            }
            const std::size_t nextIfd = p + 1 < pages.size() ? dataStart + blocksSize : 0;

            put16(static_cast<std::uint16_t>(page.entries.size()));
            std::size_t extraAt = ifdStart + ifdSize;
            std::vector<std::uint8_t> extra;
            for (const auto& entry : page.entries) {
                put16(entry.tag);
                put16(entry.type);
                put32(static_cast<std::uint32_t>(entry.values.size()));
                const std::size_t size = entry.values.size() * valueSize(entry.type);
                std::vector<std::uint8_t> valueBytes;
                std::swap(bytes_, valueBytes);
                for (std::uint32_t v : entry.values) {
                    if (entry.type == kAscii) {
                        bytes_.push_back(static_cast<std::uint8_t>(v));
                    } else if (entry.type == kShort) {
                        put16(static_cast<std::uint16_t>(v));
                    } else {
                        put32(v);
                    }
                }
                std::swap(bytes_, valueBytes);
                if (size <= 4) {
                    valueBytes.resize(4, 0);
                    bytes_.insert(bytes_.end(), valueBytes.begin(), valueBytes.end());
                } else {
                    put32(static_cast<std::uint32_t>(extraAt));
                    extraAt += size;
                    extra.insert(extra.end(), valueBytes.begin(), valueBytes.end());
                }
            }
            put32(static_cast<std::uint32_t>(nextIfd));
            bytes_.insert(bytes_.end(), extra.begin(), extra.end());
            for (const auto& block : page.blocks) {
                bytes_.insert(bytes_.end(), block.begin(), block.end());
            }
        }
        return bytes_;
    }

    /// Appends a sample of `size` bytes in the file's byte order to `out`.
    void sample(std::vector<std::uint8_t>& out, std::uint32_t value, int size) const {
        for (int i = 0; i < size; ++i) {
            const int shift = 8 * (big_ ? size - 1 - i : i);
            out.push_back(static_cast<std::uint8_t>(value >> shift));
        }
    }

private:
    void put16(std::uint16_t v) {
        std::vector<std::uint8_t> b;
        sample(b, v, 2);
        bytes_.insert(bytes_.end(), b.begin(), b.end());
    }
    void put32(std::uint32_t v) {
        std::vector<std::uint8_t> b;
        sample(b, v, 4);
        bytes_.insert(bytes_.end(), b.begin(), b.end());
    }

    bool big_;
    std::vector<std::uint8_t> bytes_;
};

std::vector<TiffEntry> baseEntries(std::uint32_t width, std::uint32_t height, std::uint32_t samples,
                                   std::uint32_t bits, std::uint32_t photometric,
                                   std::uint32_t format = 1) {
    return {{kWidth, kLong, {width}},
            {kLength, kLong, {height}},
            {kBits, kShort, std::vector<std::uint32_t>(samples, bits)},
            {kCompression, kShort, {1}},
            {kPhotometric, kShort, {photometric}},
            {kSamples, kShort, {samples}},
            {kSampleFormat, kShort, std::vector<std::uint32_t>(samples, format)}};
}

std::uint16_t twoChannelValue(int x, int y, int c) {
    return static_cast<std::uint16_t>(0x1200 + 16 * y + x + 0x4000 * c);
}

/// 5 x 4 pixels, 2 uint16 samples, big-endian, 3 rows per strip (strips of 3 and 1 rows).
std::vector<std::uint8_t> twoChannelBigEndianTiff() {
    TiffBytes tiff(/*bigEndian=*/true);
    TiffPage page;
    page.entries = baseEntries(5, 4, 2, 16, /*minisblack*/ 1);
    page.entries.push_back({kRowsPerStrip, kLong, {3}});
    page.entries.push_back({kPlanar, kShort, {1}});
    for (int y0 = 0; y0 < 4; y0 += 3) {
        std::vector<std::uint8_t> strip;
        for (int y = y0; y < std::min(4, y0 + 3); ++y) {
            for (int x = 0; x < 5; ++x) {
                for (int c = 0; c < 2; ++c) {
                    tiff.sample(strip, twoChannelValue(x, y, c), 2);
                }
            }
        }
        page.blocks.push_back(strip);
    }
    return tiff.build({page});
}

TEST_F(ImageFileTest, ReadsTwoChannelBigEndianUint16Strips) {
    writeBytes(file("two.tif"), twoChannelBigEndianTiff());
    const Result<cv::Mat> read = readImage(file("two.tif"));
    ASSERT_TRUE(read.ok()) << read.error().message;
    ASSERT_EQ(read->type(), CV_16UC2);
    ASSERT_EQ(read->size(), cv::Size(5, 4));
    for (int y = 0; y < 4; ++y) {
        for (int x = 0; x < 5; ++x) {
            for (int c = 0; c < 2; ++c) {
                EXPECT_EQ(read->at<cv::Vec2w>(y, x)[c], twoChannelValue(x, y, c))
                    << "x=" << x << " y=" << y << " c=" << c;
            }
        }
    }
}

std::uint8_t tiledValue(int x, int y) {
    return static_cast<std::uint8_t>((x * 7 + y * 13) % 256);
}

TEST_F(ImageFileTest, ReadsTiledTiffWithPartialEdgeTiles) {
    // 20 x 10 pixels in 16 x 16 tiles: the right tile and both bottoms are padded.
    TiffBytes tiff(/*bigEndian=*/false);
    TiffPage page;
    page.tiled = true;
    page.entries = baseEntries(20, 10, 1, 8, 1);
    page.entries.push_back({kTileWidth, kLong, {16}});
    page.entries.push_back({kTileLength, kLong, {16}});
    for (int tx = 0; tx < 2; ++tx) {
        std::vector<std::uint8_t> tile(16 * 16, 0xEE);
        for (int y = 0; y < 10; ++y) {
            for (int x = 0; x < 16 && tx * 16 + x < 20; ++x) {
                tile[static_cast<std::size_t>(y * 16 + x)] = tiledValue(tx * 16 + x, y);
            }
        }
        page.blocks.push_back(tile);
    }
    writeBytes(file("tiled.tif"), tiff.build({page}));
    const Result<cv::Mat> read = readImage(file("tiled.tif"));
    ASSERT_TRUE(read.ok()) << read.error().message;
    ASSERT_EQ(read->type(), CV_8UC1);
    ASSERT_EQ(read->size(), cv::Size(20, 10));
    for (int y = 0; y < 10; ++y) {
        for (int x = 0; x < 20; ++x) {
            EXPECT_EQ(read->at<std::uint8_t>(y, x), tiledValue(x, y)) << x << "," << y;
        }
    }
}

TEST_F(ImageFileTest, ReadsSeparatePlanesAndTurnsRgbIntoBgr) {
    TiffBytes tiff(/*bigEndian=*/false);
    TiffPage page;
    page.entries = baseEntries(4, 3, 3, 8, /*rgb*/ 2);
    page.entries.push_back({kRowsPerStrip, kLong, {3}});
    page.entries.push_back({kPlanar, kShort, {2}});
    for (int plane = 0; plane < 3; ++plane) { // R, G, B
        std::vector<std::uint8_t> strip;
        for (int y = 0; y < 3; ++y) {
            for (int x = 0; x < 4; ++x) {
                strip.push_back(static_cast<std::uint8_t>(plane == 0   ? 10 + x
                                                          : plane == 1 ? 100 + y
                                                                       : 200));
            }
        }
        page.blocks.push_back(strip);
    }
    writeBytes(file("planar.tif"), tiff.build({page}));
    const Result<cv::Mat> read = readImage(file("planar.tif"));
    ASSERT_TRUE(read.ok()) << read.error().message;
    ASSERT_EQ(read->type(), CV_8UC3);
    EXPECT_EQ(read->at<cv::Vec3b>(2, 3), cv::Vec3b(200, 102, 13)); // B, G, R
    EXPECT_EQ(read->at<cv::Vec3b>(0, 0), cv::Vec3b(200, 100, 10));
}

TEST_F(ImageFileTest, KeepsTheFirstFourOfFiveSamples) {
    TiffBytes tiff(/*bigEndian=*/true);
    TiffPage page;
    page.entries = baseEntries(3, 2, 5, 8, 1);
    std::vector<std::uint8_t> strip;
    for (int i = 0; i < 3 * 2; ++i) {
        for (int s = 0; s < 5; ++s) {
            strip.push_back(static_cast<std::uint8_t>(10 * i + s));
        }
    }
    page.blocks.push_back(strip);
    writeBytes(file("five.tif"), tiff.build({page}));
    const Result<cv::Mat> read = readImage(file("five.tif"));
    ASSERT_TRUE(read.ok()) << read.error().message;
    ASSERT_EQ(read->type(), CV_8UC4);
    EXPECT_EQ(read->at<cv::Vec4b>(1, 2), cv::Vec4b(50, 51, 52, 53));
}

TEST_F(ImageFileTest, ReadsTheFirstPageOfAMultiPageTiff) {
    TiffBytes tiff(/*bigEndian=*/false);
    TiffPage first;
    first.entries = baseEntries(2, 2, 1, 8, 1);
    first.blocks = {{1, 2, 3, 4}};
    TiffPage second;
    second.entries = baseEntries(3, 1, 1, 8, 1);
    second.blocks = {{9, 9, 9}};
    writeBytes(file("pages.tif"), tiff.build({first, second}));
    const Result<cv::Mat> read = readImage(file("pages.tif"));
    ASSERT_TRUE(read.ok()) << read.error().message;
    ASSERT_EQ(read->size(), cv::Size(2, 2));
    EXPECT_EQ(read->at<std::uint8_t>(1, 0), 3);
}

TiffEntry description(const std::string& text) {
    TiffEntry entry{kDescription, kAscii, {}};
    for (char c : text) {
        entry.values.push_back(static_cast<std::uint8_t>(c));
    }
    entry.values.push_back(0);
    return entry;
}

TEST_F(ImageFileTest, ReadsImageJHyperstackChannelsFromPages) {
    TiffBytes tiff(/*bigEndian=*/true);
    std::vector<TiffPage> pages;
    for (int c = 0; c < 3; ++c) { // 2 channels x 1 slice ... plus a page of another slice
        TiffPage page;
        page.entries = baseEntries(3, 2, 1, 16, 1);
        page.entries.push_back(description("ImageJ=1.54g\nimages=3\nchannels=2\nslices=2\n"));
        std::vector<std::uint8_t> strip;
        for (int i = 0; i < 6; ++i) {
            tiff.sample(strip, static_cast<std::uint32_t>(1000 * (c + 1) + i), 2);
        }
        page.blocks.push_back(strip);
        pages.push_back(page);
    }
    writeBytes(file("imagej.tif"), tiff.build(pages));
    const Result<cv::Mat> read = readImage(file("imagej.tif"));
    ASSERT_TRUE(read.ok()) << read.error().message;
    ASSERT_EQ(read->type(), CV_16UC2);
    EXPECT_EQ(read->at<cv::Vec2w>(1, 2), cv::Vec2w(1005, 2005));

    // Declares 2 channels but holds one page.
    pages.resize(1);
    writeBytes(file("imagej_cut.tif"), tiff.build(pages));
    const Result<cv::Mat> cut = readImage(file("imagej_cut.tif"));
    ASSERT_FALSE(cut.ok());
    EXPECT_EQ(cut.error().code, ErrorCode::IoError);
    EXPECT_NE(cut.error().message.find("page 1"), std::string::npos) << cut.error().message;
}

std::vector<std::uint8_t> uint32Tiff(std::uint32_t a, std::uint32_t b) {
    TiffBytes tiff(/*bigEndian=*/true);
    TiffPage page;
    page.entries = baseEntries(2, 1, 1, 32, 1, /*uint*/ 1);
    std::vector<std::uint8_t> strip;
    tiff.sample(strip, a, 4);
    tiff.sample(strip, b, 4);
    page.blocks.push_back(strip);
    return tiff.build({page});
}

TEST_F(ImageFileTest, ReadsUint32LabelsAsInt32) {
    writeBytes(file("labels.tif"), uint32Tiff(614454277u, 0));
    const Result<cv::Mat> read = readImage(file("labels.tif"));
    ASSERT_TRUE(read.ok()) << read.error().message;
    ASSERT_EQ(read->type(), CV_32SC1);
    EXPECT_EQ(read->at<std::int32_t>(0, 0), 614454277);
    EXPECT_EQ(read->at<std::int32_t>(0, 1), 0);
}

TEST_F(ImageFileTest, RejectsUint32AboveInt32Max) {
    writeBytes(file("huge.tif"), uint32Tiff(5, 0x80000000u));
    const Result<cv::Mat> read = readImage(file("huge.tif"));
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::Unsupported);
    EXPECT_NE(read.error().message.find("INT32_MAX"), std::string::npos) << read.error().message;
}

TEST_F(ImageFileTest, RejectsSignedSixteenBitSamples) {
    TiffBytes tiff(/*bigEndian=*/false);
    TiffPage page;
    page.entries = baseEntries(1, 1, 1, 16, 1, /*int*/ 2);
    page.blocks = {{1, 0}};
    writeBytes(file("int16.tif"), tiff.build({page}));
    const Result<cv::Mat> read = readImage(file("int16.tif"));
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::Unsupported);
    EXPECT_NE(read.error().message.find("int16.tif"), std::string::npos);
}

// ----------------------------------------------------------------------------------------------
// The real section series

TEST_F(ImageFileTest, ReadsRealTwoChannelSection) {
    const fs::path section =
        fs::path(SLST_SHARED_DIR) / "sections/abba-mouse-series/Section-12.tif";
    if (!fs::exists(section)) {
        GTEST_SKIP() << "shared data absent: " << section;
    }
    const Result<cv::Mat> read = readImage(section);
    ASSERT_TRUE(read.ok()) << read.error().message;
    EXPECT_EQ(read->cols, 655);
    EXPECT_EQ(read->rows, 459);
    ASSERT_EQ(read->type(), CV_16UC2);
    std::vector<cv::Mat> channels;
    cv::split(*read, channels);
    // Channel 0 shows the tissue: the centre of the section is brighter than the corners.
    const double centre = cv::mean(channels[0](cv::Rect(300, 200, 50, 50)))[0];
    const double corner = cv::mean(channels[0](cv::Rect(0, 0, 20, 20)))[0];
    EXPECT_GT(centre, 2.0 * corner + 1.0) << "centre " << centre << ", corner " << corner;
    // The sparse channel has less total signal than the tissue channel.
    EXPECT_LT(cv::mean(channels[1])[0], cv::mean(channels[0])[0]);
}

// ----------------------------------------------------------------------------------------------
// Read errors

TEST_F(ImageFileTest, MissingFileIsNotFound) {
    const Result<cv::Mat> read = readImage(file("absent.tif"));
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::NotFound);
    EXPECT_NE(read.error().message.find("absent.tif"), std::string::npos);
}

TEST_F(ImageFileTest, EmptyFileIsIoError) {
    writeBytes(file("empty.png"), {});
    const Result<cv::Mat> read = readImage(file("empty.png"));
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::IoError);
    EXPECT_NE(read.error().message.find("empty"), std::string::npos);
}

TEST_F(ImageFileTest, DirectoryIsIoError) {
    const Result<cv::Mat> read = readImage(dir_);
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::IoError);
}

TEST_F(ImageFileTest, GarbageBytesAreIoError) {
    std::vector<std::uint8_t> garbage(4096);
    std::mt19937 random(7);
    for (auto& b : garbage) {
        b = static_cast<std::uint8_t>(random());
    }
    garbage[0] = 'x'; // not accidentally a TIFF or PNG signature
    writeBytes(file("garbage.png"), garbage);
    const Result<cv::Mat> read = readImage(file("garbage.png"));
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::IoError);
}

TEST_F(ImageFileTest, GarbageAfterTiffMagicIsIoErrorAndPrintsNothing) {
    std::vector<std::uint8_t> bytes{'I', 'I', 42, 0, 0xFF, 0xFF, 0xFF, 0x7F};
    bytes.resize(64, 0xAB);
    writeBytes(file("bad.tif"), bytes);
    ::testing::internal::CaptureStderr();
    const Result<cv::Mat> read = readImage(file("bad.tif"));
    const std::string printed = ::testing::internal::GetCapturedStderr();
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::IoError);
    EXPECT_NE(read.error().message.find("libtiff"), std::string::npos) << read.error().message;
    EXPECT_EQ(printed, "");
}

TEST_F(ImageFileTest, TruncatedStripDataIsIoErrorAndPrintsNothing) {
    std::vector<std::uint8_t> bytes = twoChannelBigEndianTiff();
    bytes.resize(bytes.size() - 7); // the last strip loses its end
    writeBytes(file("cut.tif"), bytes);
    ::testing::internal::CaptureStderr();
    const Result<cv::Mat> read = readImage(file("cut.tif"));
    const std::string printed = ::testing::internal::GetCapturedStderr();
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::IoError);
    EXPECT_NE(read.error().message.find("cut.tif"), std::string::npos);
    EXPECT_NE(read.error().message.find("truncated"), std::string::npos) << read.error().message;
    EXPECT_EQ(printed, "");
}

TEST_F(ImageFileTest, TruncatedCompressedTiffIsIoError) {
    const fs::path path = file("written.tif");
    ASSERT_TRUE(writeImage(path, pattern(CV_16U, 3, 200, 200)).ok());
    std::vector<std::uint8_t> bytes = readBytes(path);
    for (std::size_t keep : {bytes.size() / 2, std::size_t{200}, std::size_t{9}}) {
        writeBytes(file("half.tif"), std::vector<std::uint8_t>(
                                         bytes.begin(), bytes.begin() + static_cast<long>(keep)));
        const Result<cv::Mat> read = readImage(file("half.tif"));
        ASSERT_FALSE(read.ok()) << "kept " << keep << " bytes";
        EXPECT_EQ(read.error().code, ErrorCode::IoError) << read.error().message;
    }
}

TEST_F(ImageFileTest, TruncatedPngIsIoError) {
    const fs::path path = file("written.png");
    ASSERT_TRUE(writeImage(path, pattern(CV_8U, 3, 200, 200)).ok());
    std::vector<std::uint8_t> bytes = readBytes(path);
    bytes.resize(bytes.size() / 2);
    writeBytes(file("half.png"), bytes);
    const Result<cv::Mat> read = readImage(file("half.png"));
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::IoError);
}

// ----------------------------------------------------------------------------------------------
// Hostile input: small files that claim huge images, non-finite floats

std::vector<std::uint8_t> deflate(const std::vector<std::uint8_t>& data) {
    uLongf size = compressBound(static_cast<uLong>(data.size()));
    std::vector<std::uint8_t> out(size);
    EXPECT_EQ(compress(out.data(), &size, data.data(), static_cast<uLong>(data.size())), Z_OK);
    out.resize(size);
    return out;
}

/// A deflate TIFF of a few hundred bytes whose header claims `width` x `height` px of 8 bits,
/// in one strip (the data holds only the first rows).
std::vector<std::uint8_t> hugeDeflateTiff(std::uint32_t width, std::uint32_t height,
                                          std::uint32_t samples = 1, std::uint32_t tileSide = 0) {
    TiffBytes tiff(/*bigEndian=*/false);
    TiffPage page;
    page.entries = baseEntries(width, height, samples, 8, /*minisblack*/ 1);
    for (auto& e : page.entries) {
        if (e.tag == kCompression)
            e.values = {8}; // adobe deflate
    }
    page.tiled = tileSide > 0;
    if (page.tiled) {
        page.entries.push_back({kTileWidth, kLong, {tileSide}});
        page.entries.push_back({kTileLength, kLong, {tileSide}});
    } else {
        page.entries.push_back({kRowsPerStrip, kLong, {height}});
    }
    page.blocks.push_back(deflate(std::vector<std::uint8_t>(4096, 0)));
    return tiff.build({page});
}

TEST_F(ImageFileTest, RefusesATinyTiffClaimingTenGigapixelsBeforeDecoding) {
    const std::vector<std::uint8_t> bytes = hugeDeflateTiff(100000, 100000);
    ASSERT_LT(bytes.size(), 1000u);
    writeBytes(file("bomb.tif"), bytes);
    const Result<cv::Mat> read = readImage(file("bomb.tif"));
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::Unsupported) << read.error().message;
    EXPECT_NE(read.error().message.find("bomb.tif"), std::string::npos) << read.error().message;
    EXPECT_NE(read.error().message.find("100000 x 100000"), std::string::npos)
        << read.error().message;
    EXPECT_NE(read.error().message.find("limit"), std::string::npos) << read.error().message;
}

TEST_F(ImageFileTest, RefusesATiffWhoseBytesExceedTheLimitThoughItsPixelsFit) {
    // 2^29 px (within the pixel limit) of 16 samples, 4 kept: 8 GiB after decoding; the strip of
    // 16 interleaved samples alone would need 8 GiB.
    writeBytes(file("wide.tif"), hugeDeflateTiff(32768, 16384, 16));
    const Result<cv::Mat> read = readImage(file("wide.tif"));
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::Unsupported) << read.error().message;
    EXPECT_NE(read.error().message.find("MiB"), std::string::npos) << read.error().message;
}

TEST_F(ImageFileTest, RefusesATileLargerThanTheLimit) {
    // 256 x 256 px in one tile of 65536 x 65536 px and 2 samples: an 8 GiB tile buffer.
    writeBytes(file("tile.tif"), hugeDeflateTiff(256, 256, 2, /*tileSide=*/65536));
    const Result<cv::Mat> read = readImage(file("tile.tif"));
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::Unsupported) << read.error().message;
}

// Found by fuzz_image: within the size limits, a few hundred bytes could still claim gigabytes
// and have them allocated before the data was found missing (3.4 GB for a 1 KB TIFF).
TEST_F(ImageFileTest, RefusesATinyTiffWhoseDataCannotHoldTheImageItClaims) {
    const std::vector<std::uint8_t> bytes =
        hugeDeflateTiff(30000, 30000); // 900 MB: within the limits
    ASSERT_LT(bytes.size(), 1000u);
    writeBytes(file("claims.tif"), bytes);
    const Result<cv::Mat> read = readImage(file("claims.tif"));
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::IoError) << read.error().message;
    EXPECT_NE(read.error().message.find("claims"), std::string::npos) << read.error().message;
    EXPECT_NE(read.error().message.find("claims.tif"), std::string::npos) << read.error().message;
}

TEST_F(ImageFileTest, ReadsAHighlyCompressedTiffThatReallyHoldsItsImage) {
    // 4000 x 4000 px of zeros, deflated to a few kilobytes: near deflate's own limit, and valid.
    const cv::Mat zeros = cv::Mat::zeros(4000, 4000, CV_8UC1);
    ASSERT_TRUE(writeImage(file("zeros.tif"), zeros).ok());
    const Result<cv::Mat> read = readImage(file("zeros.tif"));
    ASSERT_TRUE(read.ok()) << read.error().message;
    EXPECT_EQ(cv::countNonZero(*read), 0);
    EXPECT_EQ(read->size(), zeros.size());
    ASSERT_TRUE(cv::imwrite(file("zeros.png").string(), zeros, {cv::IMWRITE_PNG_COMPRESSION, 9}));
    const Result<cv::Mat> png = readImage(file("zeros.png"));
    ASSERT_TRUE(png.ok()) << png.error().message;
    EXPECT_EQ(png->size(), zeros.size());
    ASSERT_TRUE(cv::imwrite(file("zeros.jpg").string(), zeros));
    const Result<cv::Mat> jpeg = readImage(file("zeros.jpg"));
    ASSERT_TRUE(jpeg.ok()) << jpeg.error().message;
    EXPECT_EQ(jpeg->size(), zeros.size());
}

/// A PNG whose IHDR claims `width` x `height` RGBA16 pixels, with one tiny IDAT.
std::vector<std::uint8_t> hugePng(std::uint32_t width, std::uint32_t height) {
    std::vector<std::uint8_t> out{0x89, 'P', 'N', 'G', '\r', '\n', 0x1A, '\n'};
    const auto put32 = [](std::vector<std::uint8_t>& v, std::uint32_t x) {
        for (int shift = 24; shift >= 0; shift -= 8)
            v.push_back(static_cast<std::uint8_t>(x >> shift));
    };
    const auto chunk = [&](const char* type, const std::vector<std::uint8_t>& data) {
        put32(out, static_cast<std::uint32_t>(data.size()));
        std::vector<std::uint8_t> body(type, type + 4);
        body.insert(body.end(), data.begin(), data.end());
        out.insert(out.end(), body.begin(), body.end());
        put32(out,
              static_cast<std::uint32_t>(crc32(0, body.data(), static_cast<uInt>(body.size()))));
    };
    std::vector<std::uint8_t> ihdr;
    put32(ihdr, width);
    put32(ihdr, height);
    ihdr.insert(ihdr.end(), {16, 6, 0, 0, 0}); // 16 bits, RGBA, deflate, no filter, no interlace
    chunk("IHDR", ihdr);
    chunk("IDAT", deflate(std::vector<std::uint8_t>(4096, 0)));
    chunk("IEND", {});
    return out;
}

TEST_F(ImageFileTest, RefusesATinyPngClaimingMoreBytesThanTheLimit) {
    // 30000 x 30000 < 2^30 px, so OpenCV's own pixel limit lets it through: 7.2 GB of RGBA16.
    writeBytes(file("bomb.png"), hugePng(30000, 30000));
    const Result<cv::Mat> read = readImage(file("bomb.png"));
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::Unsupported) << read.error().message;
    EXPECT_NE(read.error().message.find("30000 x 30000"), std::string::npos)
        << read.error().message;
}

TEST_F(ImageFileTest, RefusesATinyPngOrJpegWhoseDataCannotHoldTheImageItClaims) {
    // 20000 x 20000 RGBA16: 3.2 GB, within the limits, from a file of a few hundred bytes.
    writeBytes(file("claims.png"), hugePng(20000, 20000));
    Result<cv::Mat> read = readImage(file("claims.png"));
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::IoError) << read.error().message;
    EXPECT_NE(read.error().message.find("claims"), std::string::npos) << read.error().message;

    // A real 16 x 16 JPEG whose frame header is changed to claim 30000 x 30000 px (2.7 GB).
    std::vector<std::uint8_t> jpeg;
    ASSERT_TRUE(cv::imencode(".jpg", cv::Mat(16, 16, CV_8UC3, cv::Scalar(40, 80, 120)), jpeg));
    std::uint8_t* sof = testing_jpeg::findSof0(jpeg.data(), jpeg.size());
    ASSERT_NE(sof, nullptr);
    testing_jpeg::claimSize(sof, 30000, 30000);
    writeBytes(file("claims.jpg"), jpeg);
    read = readImage(file("claims.jpg"));
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::IoError) << read.error().message;
    EXPECT_NE(read.error().message.find("30000 x 30000"), std::string::npos)
        << read.error().message;
}

TEST_F(ImageFileTest, RefusesFormatsOtherThanTiffPngAndJpegBeforeTheyAllocate) {
    // A 60-byte Radiance HDR claiming 20000 x 20000 px: OpenCV would allocate 4.8 GB of floats
    // from the header (what the fuzzer found on 2026-12-03). It is not read at all.
    const std::string hdr =
        "#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 20000 +X 20000\n\x02\x02\x4e\x20\x80\x01";
    writeBytes(file("bomb.hdr"), std::vector<std::uint8_t>(hdr.begin(), hdr.end()));
    Result<cv::Mat> read = readImage(file("bomb.hdr"));
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::IoError) << read.error().message;
    EXPECT_NE(read.error().message.find("not a TIFF, PNG or JPEG"), std::string::npos)
        << read.error().message;

    // A real, small BMP is refused the same way: it is no format sections come in.
    std::vector<std::uint8_t> bmp;
    ASSERT_TRUE(cv::imencode(".bmp", cv::Mat(16, 16, CV_8UC3, cv::Scalar(1, 2, 3)), bmp));
    writeBytes(file("small.bmp"), bmp);
    read = readImage(file("small.bmp"));
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::IoError) << read.error().message;

    // An arithmetic-coded JPEG (SOF9) has no floor on the bits a block takes: refused by name.
    std::vector<std::uint8_t> jpeg;
    ASSERT_TRUE(cv::imencode(".jpg", cv::Mat(16, 16, CV_8UC3, cv::Scalar(40, 80, 120)), jpeg));
    std::uint8_t* sof = testing_jpeg::findSof0(jpeg.data(), jpeg.size());
    ASSERT_NE(sof, nullptr);
    sof[1] = 0xC9;
    writeBytes(file("arithmetic.jpg"), jpeg);
    read = readImage(file("arithmetic.jpg"));
    ASSERT_FALSE(read.ok());
    EXPECT_EQ(read.error().code, ErrorCode::Unsupported) << read.error().message;
    EXPECT_NE(read.error().message.find("arithmetic"), std::string::npos) << read.error().message;

    // The formats that are read still are: a PNG and a JPEG of the same 16 x 16 image.
    for (const char* ext : {".png", ".jpg"}) {
        std::vector<std::uint8_t> bytes;
        ASSERT_TRUE(cv::imencode(ext, cv::Mat(16, 16, CV_8UC3, cv::Scalar(40, 80, 120)), bytes));
        writeBytes(file(std::string("good") + ext), bytes);
        const Result<cv::Mat> good = readImage(file(std::string("good") + ext));
        ASSERT_TRUE(good.ok()) << ext << ": " << good.error().message;
        EXPECT_EQ(good->size(), cv::Size(16, 16));
    }
}

TEST_F(ImageFileTest, RefusesNanAndInfinityInFloatImagesNamingTheFile) {
    for (const float bad :
         {std::numeric_limits<float>::quiet_NaN(), std::numeric_limits<float>::infinity(),
          -std::numeric_limits<float>::infinity()}) {
        cv::Mat image(40, 50, CV_32FC2, cv::Scalar(1.0f, 2.0f));
        image.at<cv::Vec2f>(7, 11)[1] = bad;
        ASSERT_TRUE(writeImage(file("float.tif"), image).ok());
        const Result<cv::Mat> read = readImage(file("float.tif"));
        ASSERT_FALSE(read.ok()) << bad;
        EXPECT_EQ(read.error().code, ErrorCode::InvalidArgument) << read.error().message;
        EXPECT_NE(read.error().message.find("float.tif"), std::string::npos);
        EXPECT_NE(read.error().message.find("x=11, y=7"), std::string::npos)
            << read.error().message;
    }
    cv::Mat finite(40, 50, CV_32FC1, cv::Scalar(-3.5f));
    ASSERT_TRUE(writeImage(file("finite.tif"), finite).ok());
    EXPECT_TRUE(readImage(file("finite.tif")).ok());
}

// ----------------------------------------------------------------------------------------------
// Write errors

void expectWriteError(const Result<void>& result, ErrorCode code) {
    ASSERT_FALSE(result.ok());
    EXPECT_EQ(result.error().code, code) << result.error().message;
}

TEST_F(ImageFileTest, RejectsImagesTheFormatCannotHold) {
    expectWriteError(writeImage(file("empty.png"), cv::Mat()), ErrorCode::InvalidArgument);
    expectWriteError(writeImage(file("float.png"), pattern(CV_32F, 1)), ErrorCode::Unsupported);
    expectWriteError(writeImage(file("two.png"), pattern(CV_8U, 2)), ErrorCode::Unsupported);
    cv::Mat five(3, 3, CV_8UC(5));
    five.reshape(1).setTo(1);
    expectWriteError(writeImage(file("five.tif"), five), ErrorCode::Unsupported);
    expectWriteError(writeImage(file("double.tif"), cv::Mat(3, 3, CV_64F, cv::Scalar(1))),
                     ErrorCode::Unsupported);
    expectWriteError(writeImage(file("image.jpg"), pattern(CV_8U, 1)), ErrorCode::Unsupported);
    expectWriteError(writeImage(file("noextension"), pattern(CV_8U, 1)), ErrorCode::Unsupported);
    EXPECT_TRUE(entries().empty()) << "nothing may be left behind";
}

TEST_F(ImageFileTest, RejectsNegativeLabels) {
    cv::Mat labels(4, 4, CV_32S, cv::Scalar(7));
    labels.at<std::int32_t>(2, 1) = -3;
    const Result<void> written = writeImage(file("labels.tif"), labels);
    expectWriteError(written, ErrorCode::InvalidArgument);
    EXPECT_NE(written.error().message.find("row 2"), std::string::npos) << written.error().message;
    EXPECT_TRUE(entries().empty());
}

TEST_F(ImageFileTest, MissingDirectoryIsNotFound) {
    const Result<void> written = writeImage(file("no/such/dir/image.tif"), pattern(CV_8U, 1));
    expectWriteError(written, ErrorCode::NotFound);
    EXPECT_NE(written.error().message.find("no/such/dir"), std::string::npos);
}

} // namespace
} // namespace slicestation::core
