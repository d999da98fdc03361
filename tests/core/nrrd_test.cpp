#include "slicestation/core/nrrd.hpp"

#include "../common/test_dir.hpp"

#include <gtest/gtest.h>
#include <zlib.h>

#include <cstdint>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

namespace slicestation::core {
namespace {

namespace fs = std::filesystem;

const fs::path kAtlasDir = fs::path(SLST_SHARED_DIR) / "atlas/allen-ccf-2017";

std::vector<std::uint8_t> gzipBytes(const std::vector<std::uint8_t>& raw) {
    z_stream stream{};
    // 31 = 15-bit window + gzip header, as in the Allen files.
    EXPECT_EQ(deflateInit2(&stream, Z_BEST_SPEED, Z_DEFLATED, 31, 8, Z_DEFAULT_STRATEGY), Z_OK);
    std::vector<std::uint8_t> out(deflateBound(&stream, static_cast<uLong>(raw.size())) + 64);
    stream.next_in = const_cast<Bytef*>(raw.data());
    stream.avail_in = static_cast<uInt>(raw.size());
    stream.next_out = out.data();
    stream.avail_out = static_cast<uInt>(out.size());
    EXPECT_EQ(deflate(&stream, Z_FINISH), Z_STREAM_END);
    out.resize(stream.total_out);
    deflateEnd(&stream);
    return out;
}

/// Values 0..n-1 (times a factor), so that each voxel tells where it came from.
std::vector<std::uint32_t> ramp(std::size_t n, std::uint32_t factor) {
    std::vector<std::uint32_t> values(n);
    for (std::size_t i = 0; i < n; ++i) {
        values[i] = static_cast<std::uint32_t>(i) * factor;
    }
    return values;
}

std::vector<std::uint8_t> encode(const std::vector<std::uint32_t>& values, int bytes, bool big) {
    std::vector<std::uint8_t> out;
    for (std::uint32_t v : values) {
        for (int i = 0; i < bytes; ++i) {
            const int shift = 8 * (big ? bytes - 1 - i : i);
            out.push_back(static_cast<std::uint8_t>(v >> shift));
        }
    }
    return out;
}

class NrrdTest : public testing_dir::TempDirTest {
protected:
    NrrdTest() : TempDirTest("nrrd") {}

    fs::path write(const std::string& name, const std::string& header,
                   const std::vector<std::uint8_t>& data = {}) const {
        const fs::path path = dir_ / name;
        std::ofstream out(path, std::ios::binary);
        out << header;
        out.write(reinterpret_cast<const char*>(data.data()),
                  static_cast<std::streamsize>(data.size()));
        return path;
    }

    /// A valid 4 x 3 x 2 header with one line replaced or added.
    static std::string header(const std::string& type, const std::string& encoding,
                              const std::string& extraLines = "",
                              const std::string& endian = "little") {
        return "NRRD0004\n# a comment\ntype: " + type +
               "\ndimension: 3\nsizes: 4 3 2\nspace directions: (20,0,0) (0,30,0) (0,0,40)\n"
               "endian: " +
               endian + "\nencoding: " + encoding + "\nsome key:=some value\n" + extraLines + "\n";
    }

    void expectError(const fs::path& path, ErrorCode code, const std::string& mention) const {
        const Result<Volume> volume = readNrrd(path);
        ASSERT_FALSE(volume.ok()) << path;
        EXPECT_EQ(volume.error().code, code) << volume.error().message;
        EXPECT_NE(volume.error().message.find(mention), std::string::npos)
            << "'" << volume.error().message << "' should mention '" << mention << "'";
        EXPECT_NE(volume.error().message.find(path.filename().string()), std::string::npos)
            << volume.error().message;
    }
};

TEST_F(NrrdTest, ReadsRawLittleEndianUint16WithSpacing) {
    const auto values = ramp(24, 1000);
    const auto path = write("u16.nrrd", header("unsigned short", "raw"), encode(values, 2, false));
    const Result<Volume> volume = readNrrd(path);
    ASSERT_TRUE(volume.ok()) << volume.error().message;
    EXPECT_EQ(volume->sizes, (std::array<int, 3>{4, 3, 2}));
    EXPECT_EQ(volume->spacingUm, (std::array<double, 3>{20, 30, 40}));
    EXPECT_EQ(volume->type, "unsigned short");
    EXPECT_EQ(volume->data, values);
    EXPECT_EQ(volume->at(3, 2, 1), 23000u); // i0 + 4 * (i1 + 3 * i2) = 23
    EXPECT_EQ(volume->at(1, 2, 0), 9000u);
}

TEST_F(NrrdTest, ReadsRawBigEndianUint32AndSpacingsField) {
    const auto values = ramp(24, 100000001);
    const std::string text = "NRRD0001\ntype: uint32\ndimension: 3\nsizes: 4 3 2\n"
                             "spacings: 10 nan 25.5\nendian: big\nencoding: raw\n\n";
    const auto path = write("u32.nrrd", text, encode(values, 4, true));
    const Result<Volume> volume = readNrrd(path);
    ASSERT_TRUE(volume.ok()) << volume.error().message;
    EXPECT_EQ(volume->data, values);
    EXPECT_EQ(volume->spacingUm, (std::array<double, 3>{10, 0, 25.5}));
}

TEST_F(NrrdTest, ReadsGzipBigEndianInt16AndUint8WithCrLf) {
    const auto values = ramp(24, 1300); // up to 29900 < 32767
    const auto path16 =
        write("i16.nrrd", header("short", "gzip", "", "big"), gzipBytes(encode(values, 2, true)));
    const Result<Volume> v16 = readNrrd(path16);
    ASSERT_TRUE(v16.ok()) << v16.error().message;
    EXPECT_EQ(v16->data, values);

    const auto bytes = ramp(24, 10);
    std::string crlf = "NRRD0005\r\ntype: uchar\r\ndimension: 3\r\nsizes: 4 3 2\r\n"
                       "encoding: gz\r\n\r\n"; // no endian: not needed for one byte
    const auto path8 = write("u8.nrrd", crlf, gzipBytes(encode(bytes, 1, false)));
    const Result<Volume> v8 = readNrrd(path8);
    ASSERT_TRUE(v8.ok()) << v8.error().message;
    EXPECT_EQ(v8->data, bytes);
    EXPECT_EQ(v8->spacingUm, (std::array<double, 3>{0, 0, 0}));
}

TEST_F(NrrdTest, MissingFileIsNotFound) {
    const Result<Volume> volume = readNrrd(dir_ / "absent.nrrd");
    ASSERT_FALSE(volume.ok());
    EXPECT_EQ(volume.error().code, ErrorCode::NotFound);
    EXPECT_NE(volume.error().message.find("absent.nrrd"), std::string::npos);
}

TEST_F(NrrdTest, EmptyFileIsIoError) {
    expectError(write("empty.nrrd", ""), ErrorCode::IoError, "empty");
}

TEST_F(NrrdTest, WrongMagicIsInvalidArgument) {
    expectError(write("png.nrrd", "\x89PNG\r\n\x1a\n"), ErrorCode::InvalidArgument, "NRRD");
}

TEST_F(NrrdTest, BadHeaderFieldsAreNamed) {
    const auto data = encode(ramp(24, 1), 2, false);
    expectError(write("sizes.nrrd",
                      "NRRD0004\ntype: ushort\ndimension: 3\nsizes: 4 x 2\n"
                      "endian: little\nencoding: raw\n\n",
                      data),
                ErrorCode::InvalidArgument, "'sizes'");
    expectError(write("sizes2.nrrd",
                      "NRRD0004\ntype: ushort\ndimension: 3\nsizes: 4 3\n"
                      "endian: little\nencoding: raw\n\n",
                      data),
                ErrorCode::InvalidArgument, "'sizes'");
    expectError(write("dim.nrrd",
                      "NRRD0004\ntype: ushort\ndimension: 2\nsizes: 12 2\n"
                      "endian: little\nencoding: raw\n\n",
                      data),
                ErrorCode::Unsupported, "'dimension'");
    expectError(write("dimtext.nrrd",
                      "NRRD0004\ntype: ushort\ndimension: three\nsizes: 4 3 2\n"
                      "endian: little\nencoding: raw\n\n",
                      data),
                ErrorCode::InvalidArgument, "'dimension'");
    expectError(write("float.nrrd", header("float", "raw"), data), ErrorCode::Unsupported,
                "'type'");
    expectError(write("banana.nrrd", header("banana", "raw"), data), ErrorCode::InvalidArgument,
                "'type'");
    expectError(write("bzip.nrrd", header("ushort", "bzip2"), data), ErrorCode::Unsupported,
                "'encoding'");
    expectError(write("enc.nrrd", header("ushort", "zip-it"), data), ErrorCode::InvalidArgument,
                "'encoding'");
    expectError(write("endian.nrrd", header("ushort", "raw", "", "middle"), data),
                ErrorCode::InvalidArgument, "'endian'");
    expectError(write("noendian.nrrd",
                      "NRRD0004\ntype: ushort\ndimension: 3\nsizes: 4 3 2\n"
                      "encoding: raw\n\n",
                      data),
                ErrorCode::InvalidArgument, "'endian'");
    expectError(write("notype.nrrd",
                      "NRRD0004\ndimension: 3\nsizes: 4 3 2\nendian: little\n"
                      "encoding: raw\n\n",
                      data),
                ErrorCode::InvalidArgument, "'type'");
    expectError(write("dirs.nrrd",
                      "NRRD0004\ntype: ushort\ndimension: 3\nsizes: 4 3 2\n"
                      "space directions: (20,0,0) (0,abc,0) (0,0,40)\n"
                      "endian: little\nencoding: raw\n\n",
                      data),
                ErrorCode::InvalidArgument, "'space directions'");
    expectError(write("dirs2.nrrd",
                      "NRRD0004\ntype: ushort\ndimension: 3\nsizes: 4 3 2\n"
                      "space directions: (20,0,0) (0,30,0)\n"
                      "endian: little\nencoding: raw\n\n",
                      data),
                ErrorCode::InvalidArgument, "'space directions'");
    expectError(write("noline.nrrd", header("ushort", "raw", "this is not a field\n"), data),
                ErrorCode::InvalidArgument, "line 10");
    expectError(write("twice.nrrd", header("ushort", "raw", "type: uint8\n"), data),
                ErrorCode::InvalidArgument, "twice");
    expectError(write("skip.nrrd", header("ushort", "raw", "byte skip: 16\n"), data),
                ErrorCode::Unsupported, "'byte skip'");
}

TEST_F(NrrdTest, DetachedDataFileIsUnsupported) {
    const std::string text = "NRRD0004\ntype: ushort\ndimension: 3\nsizes: 4 3 2\n"
                             "endian: little\nencoding: raw\ndata file: volume.raw\n";
    expectError(write("detached.nhdr", text), ErrorCode::Unsupported, "'data file'");
}

TEST_F(NrrdTest, HeaderWithoutBlankLineIsIoError) {
    expectError(write("cut.nrrd", "NRRD0004\ntype: ushort\ndimension: 3\nsizes: 4"),
                ErrorCode::IoError, "blank line");
}

TEST_F(NrrdTest, TruncatedRawDataIsIoError) {
    auto data = encode(ramp(24, 1), 2, false);
    data.resize(data.size() - 1);
    expectError(write("short.nrrd", header("ushort", "raw"), data), ErrorCode::IoError,
                "truncated");
}

TEST_F(NrrdTest, TruncatedGzipDataIsIoError) {
    auto data = gzipBytes(encode(ramp(24, 77), 4, false));
    data.resize(data.size() - 10); // loses the tail of the deflate stream and the trailer
    expectError(write("short.nrrd", header("uint", "gzip"), data), ErrorCode::IoError, "truncated");
}

TEST_F(NrrdTest, CorruptGzipDataIsIoError) {
    const std::vector<std::uint8_t> garbage{0x1f, 0x8b, 8,    0, 0, 0, 0, 0, 0, 3, 0xFF,
                                            0xFF, 0xFF, 0xFF, 1, 2, 3, 4, 5, 6, 7, 8};
    expectError(write("corrupt.nrrd", header("uint", "gzip"), garbage), ErrorCode::IoError, "gzip");
}

TEST_F(NrrdTest, GzipWithMoreDataThanSizesIsIoError) {
    const auto data = gzipBytes(encode(ramp(25, 1), 4, false));
    expectError(write("long.nrrd", header("uint", "gzip"), data), ErrorCode::IoError, "more");
}

TEST_F(NrrdTest, SmallGzipClaimingAVolumeBeyondTheLimitIsRefusedBeforeInflating) {
    // 70 KB of gzip that claims 1000^3 voxels: 4 GB as 32-bit labels, twice the limit.
    const auto data = gzipBytes(std::vector<std::uint8_t>(16u << 20, 0));
    ASSERT_LT(data.size(), 100u << 10);
    expectError(write("bomb.nrrd",
                      "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 1000 1000 1000\n"
                      "spacings: 25 25 25\nencoding: gzip\n\n",
                      data),
                ErrorCode::Unsupported, "limit");
}

TEST_F(NrrdTest, GzipFarShorterThanTheClaimedSizeIsIoErrorBeforeInflating) {
    // 400^3 bytes claimed (within the limit), a few hundred bytes given: no deflate stream of
    // that length holds 64 MB.
    const auto data = gzipBytes(std::vector<std::uint8_t>(4096, 0));
    expectError(write("short.nrrd",
                      "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 400 400 400\n"
                      "spacings: 25 25 25\nencoding: gzip\n\n",
                      data),
                ErrorCode::IoError, "cannot hold");
}

TEST_F(NrrdTest, GzipOfTheRightRatioButEndingEarlyIsTruncated) {
    // 1 MB of zeros compresses ~1000:1: the ratio check passes; the stream then ends early.
    const auto data = gzipBytes(std::vector<std::uint8_t>(1u << 20, 0));
    expectError(write("early.nrrd",
                      "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 128 128 128\n"
                      "spacings: 25 25 25\nencoding: gzip\n\n",
                      data),
                ErrorCode::IoError, "bytes");
}

TEST_F(NrrdTest, FileLargerThanTheVolumeLimitIsRefusedUnread) {
    const fs::path path = write("huge.nrrd", header("uint8", "raw"));
    // Sparse: costs no disk, and the reader must not read it.
    fs::resize_file(path, kMaxVolumeBytes + (std::uint64_t{4} << 20));
    expectError(path, ErrorCode::Unsupported, "limit");
}

TEST_F(NrrdTest, VoxelSizesOutOfRangeAreNamed) {
    const auto data = encode(ramp(24, 1), 2, false);
    const std::string start = "NRRD0004\ntype: ushort\ndimension: 3\nsizes: 4 3 2\n";
    const std::string end = "endian: little\nencoding: raw\n\n";
    expectError(write("hugedir.nrrd",
                      start + "space directions: (1e300,1e300,0) (0,30,0) (0,0,40)\n" + end, data),
                ErrorCode::InvalidArgument, "'space directions'");
    expectError(write("tinydir.nrrd",
                      start + "space directions: (1e-9,0,0) (0,30,0) (0,0,40)\n" + end, data),
                ErrorCode::InvalidArgument, "'space directions'");
    expectError(write("hugesp.nrrd", start + "spacings: 25 1e9 25\n" + end, data),
                ErrorCode::InvalidArgument, "'spacings'");
    expectError(write("tinysp.nrrd", start + "spacings: 25 25 1e-7\n" + end, data),
                ErrorCode::InvalidArgument, "'spacings'");
}

TEST_F(NrrdTest, NegativeSignedVoxelIsAnError) {
    auto values = ramp(24, 3);
    values[4 * (1 + 3 * 1) + 2] = 0xFFFFFFFFu; // -1 at (2, 1, 1)
    expectError(write("neg.nrrd", header("int32", "raw"), encode(values, 4, false)),
                ErrorCode::Unsupported, "(2, 1, 1)");
}

TEST_F(NrrdTest, RealFileTruncatedIsIoError) {
    const fs::path real = kAtlasDir / "annotation_100.nrrd";
    if (!fs::exists(real)) {
        GTEST_SKIP() << "shared data absent: " << real;
    }
    std::ifstream in(real, std::ios::binary);
    std::vector<std::uint8_t> bytes{std::istreambuf_iterator<char>(in),
                                    std::istreambuf_iterator<char>()};
    bytes.resize(bytes.size() * 2 / 3);
    expectError(write("annotation_cut.nrrd", "", bytes), ErrorCode::IoError, "truncated");
}

TEST(RealAtlas, Annotation50HasAllenGridAndLabels) {
    const fs::path path = kAtlasDir / "annotation_50.nrrd";
    if (!fs::exists(path)) {
        GTEST_SKIP() << "shared data absent: " << path;
    }
    const Result<Volume> volume = readNrrd(path);
    ASSERT_TRUE(volume.ok()) << volume.error().message;
    EXPECT_EQ(volume->sizes, (std::array<int, 3>{264, 160, 228}));
    EXPECT_EQ(volume->spacingUm, (std::array<double, 3>{50, 50, 50}));
    EXPECT_EQ(volume->type, "unsigned int");
    ASSERT_EQ(volume->data.size(), 264u * 160u * 228u);
    EXPECT_EQ(volume->at(0, 0, 0), 0u);        // corner: outside the brain
    EXPECT_EQ(volume->at(263, 159, 227), 0u);  // opposite corner
    EXPECT_NE(volume->at(132, 80, 114), 0u);   // centre of the brain
    EXPECT_EQ(volume->at(100, 70, 84), 672u);  // Caudoputamen, left striatum
    EXPECT_EQ(volume->at(110, 60, 114), 310u); // Septofimbrial nucleus at the midline
}

TEST(RealAtlas, Annotation100AndTemplateShareTheGrid) {
    const fs::path annotationPath = kAtlasDir / "annotation_100.nrrd";
    const fs::path templatePath = kAtlasDir / "average_template_100.nrrd";
    if (!fs::exists(annotationPath) || !fs::exists(templatePath)) {
        GTEST_SKIP() << "shared data absent: " << kAtlasDir;
    }
    const Result<Volume> annotation = readNrrd(annotationPath);
    const Result<Volume> average = readNrrd(templatePath);
    ASSERT_TRUE(annotation.ok()) << annotation.error().message;
    ASSERT_TRUE(average.ok()) << average.error().message;
    EXPECT_EQ(annotation->sizes, (std::array<int, 3>{132, 80, 114}));
    EXPECT_EQ(average->sizes, annotation->sizes);
    EXPECT_EQ(average->spacingUm, (std::array<double, 3>{100, 100, 100}));
    EXPECT_EQ(average->type, "unsigned short");
    EXPECT_EQ(average->at(66, 40, 57), 153u);
    EXPECT_EQ(annotation->at(66, 40, 57), 59u);
    // uint16 template: every value fits 16 bits, and brain voxels are brighter than outside.
    std::uint64_t inside = 0;
    std::uint64_t outside = 0;
    std::uint64_t insideCount = 0;
    for (std::size_t i = 0; i < average->data.size(); ++i) {
        ASSERT_LE(average->data[i], 65535u);
        if (annotation->data[i] != 0) {
            inside += average->data[i];
            ++insideCount;
        } else {
            outside += average->data[i];
        }
    }
    ASSERT_GT(insideCount, 0u);
    EXPECT_GT(inside / insideCount, 3 * outside / (average->data.size() - insideCount));
}

} // namespace
} // namespace slicestation::core
