// The OME-TIFF layout QuPath and ABBA read (issue 22 item 5): 512 px tiles, reduced levels in
// SubIFDs, BigTIFF when forced or past the threshold, and the OME-XML's metadata, checked with
// libtiff directly (not only through our own reader) and against the OME schema's rules that
// Bio-Formats relies on.
#include "../../common/test_dir.hpp"
#include "slicestation/core/image_file.hpp"
#include "slicestation/core/tiff_file.hpp"
#include "slicestation/daemon/storage/ome_tiff.hpp"
#include "slicestation/daemon/version.hpp"

#include <gtest/gtest.h>

#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include <pugixml.hpp>

#include <tiffio.h>

#include <stdlib.h>

#include <array>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <regex>
#include <string>
#include <tuple>
#include <vector>

namespace slicestation::test {
namespace {

namespace fs = std::filesystem;
using core::ErrorCode;
using daemon::OmeTiffInfo;
using daemon::OmeTiffLayout;

/// A smooth gradient with noise: reduced levels differ from nearest-neighbour picks.
cv::Mat sectionLike(int type, int width, int height) {
    cv::Mat m(height, width, type);
    cv::RNG rng(7);
    rng.fill(m, cv::RNG::UNIFORM, 0, CV_MAT_DEPTH(type) == CV_16U ? 20000 : 80);
    const double scale = CV_MAT_DEPTH(type) == CV_16U ? 40000.0 : 170.0;
    cv::Mat ramp(height, width, CV_MAKETYPE(CV_MAT_DEPTH(type), CV_MAT_CN(type)));
    for (int y = 0; y < height; ++y)
        for (int x = 0; x < width; ++x) {
            const double v = scale * (0.5 + 0.5 * std::sin(x * 0.01) * std::cos(y * 0.013));
            if (CV_MAT_DEPTH(type) == CV_16U)
                ramp.ptr<std::uint16_t>(y)[x * CV_MAT_CN(type)] = static_cast<std::uint16_t>(v);
            else
                ramp.ptr<std::uint8_t>(y)[x * CV_MAT_CN(type)] = static_cast<std::uint8_t>(v);
        }
    return m + ramp;
}

OmeTiffInfo pyramidInfo() {
    OmeTiffInfo info;
    info.umPerPx = 1.6;
    info.stage = {40'000, 21'500.5, 2'480};
    info.channel = "DAPI";
    info.channelRgba = 0x0000FFFFu; // blue
    info.objective = "4x";
    info.name = "slide1-s03";
    info.exposureUs = 20'000;
    info.acquiredUtc = "2026-12-02T05:00:00Z";
    return info;
}

/// Every tile of a level put back together through core::readTiffTile.
cv::Mat assembleLevel(const fs::path& file, int level, cv::Size size, int tile, int type) {
    cv::Mat out(size, type, cv::Scalar::all(0));
    for (int ty = 0; ty * tile < size.height; ++ty)
        for (int tx = 0; tx * tile < size.width; ++tx) {
            auto t = core::readTiffTile(file, level, tx, ty);
            EXPECT_TRUE(t) << t.error().message;
            if (!t)
                return {};
            t->copyTo(out(cv::Rect(tx * tile, ty * tile, t->cols, t->rows)));
        }
    return out;
}

struct RawLevel {
    std::uint32_t width = 0, height = 0, tileW = 0, tileH = 0, subfileType = 0;
    std::uint16_t compression = 0;
};

RawLevel rawLevel(TIFF* tif) {
    RawLevel l;
    TIFFGetField(tif, TIFFTAG_IMAGEWIDTH, &l.width);
    TIFFGetField(tif, TIFFTAG_IMAGELENGTH, &l.height);
    TIFFGetField(tif, TIFFTAG_TILEWIDTH, &l.tileW);
    TIFFGetField(tif, TIFFTAG_TILELENGTH, &l.tileH);
    TIFFGetFieldDefaulted(tif, TIFFTAG_SUBFILETYPE, &l.subfileType);
    TIFFGetField(tif, TIFFTAG_COMPRESSION, &l.compression);
    return l;
}

class OmePyramid : public ::testing::TestWithParam<int> {};

TEST_P(OmePyramid, TiledLevelsInSubIfdsAreAreaReductionsOfTheFullImage) {
    testing_dir::ScratchDir dir("pyr");
    const fs::path file = dir.path() / "big.ome.tif";
    // 2600 px: levels 2600, 1300, 650 (the last fits in 1024 px).
    const cv::Mat image = sectionLike(GetParam(), 2600, 1900);
    ASSERT_TRUE(daemon::writeOmeTiffAtomic(file, image, pyramidInfo()));

    // libtiff directly: one main IFD, tiled 512 x 512, two SubIFDs marked reduced-resolution.
    TIFF* tif = TIFFOpen(file.c_str(), "r");
    ASSERT_NE(tif, nullptr);
    EXPECT_EQ(TIFFNumberOfDirectories(tif), 1) << "levels must not be pages of their own";
    EXPECT_EQ(TIFFIsBigTIFF(tif), 0);
    EXPECT_NE(TIFFIsTiled(tif), 0);
    const RawLevel full = rawLevel(tif);
    EXPECT_EQ(full.width, 2600u);
    EXPECT_EQ(full.tileW, 512u);
    EXPECT_EQ(full.tileH, 512u);
    EXPECT_EQ(full.subfileType, 0u);
    std::uint16_t count = 0;
    toff_t* offsetsPtr = nullptr;
    ASSERT_EQ(TIFFGetField(tif, TIFFTAG_SUBIFD, &count, &offsetsPtr), 1);
    ASSERT_EQ(count, 2);
    const std::vector<toff_t> offsets(offsetsPtr, offsetsPtr + count);
    const std::vector<cv::Size> expected{{1300, 950}, {650, 475}};
    for (int k = 0; k < count; ++k) {
        EXPECT_GT(offsets[k], 8u);
        EXPECT_LT(offsets[k], fs::file_size(file));
        ASSERT_EQ(TIFFSetSubDirectory(tif, offsets[k]), 1);
        const RawLevel l = rawLevel(tif);
        EXPECT_EQ(l.width, static_cast<std::uint32_t>(expected[k].width));
        EXPECT_EQ(l.height, static_cast<std::uint32_t>(expected[k].height));
        EXPECT_EQ(l.tileW, 512u);
        EXPECT_EQ(l.tileH, 512u);
        EXPECT_EQ(l.subfileType, static_cast<std::uint32_t>(FILETYPE_REDUCEDIMAGE));
        EXPECT_EQ(l.compression, COMPRESSION_ADOBE_DEFLATE);
    }
    TIFFClose(tif);

    // Our reader agrees, and the pixels of every level are INTER_AREA reductions of the full.
    auto info = core::readTiffPyramidInfo(file);
    ASSERT_TRUE(info) << info.error().message;
    ASSERT_EQ(info->levels.size(), 3u);
    EXPECT_EQ(info->subIfdOffsets, std::vector<std::uint64_t>(offsets.begin(), offsets.end()));
    EXPECT_EQ(info->levels[0], cv::Size(2600, 1900));
    EXPECT_EQ(info->cvType, image.type());
    EXPECT_EQ(
        cv::norm(assembleLevel(file, 0, info->levels[0], 512, image.type()), image, cv::NORM_INF),
        0.0);
    for (int k = 1; k <= 2; ++k) {
        EXPECT_EQ(info->levels[k], expected[k - 1]);
        cv::Mat reference;
        cv::resize(image, reference, expected[k - 1], 0, 0, cv::INTER_AREA);
        const cv::Mat got = assembleLevel(file, k, expected[k - 1], 512, image.type());
        ASSERT_EQ(got.size(), reference.size());
        EXPECT_EQ(cv::norm(got, reference, cv::NORM_INF), 0.0) << "level " << k;
    }
    // The full image still reads as before (first IFD), with its metadata.
    auto back = daemon::readOmeTiff(file);
    ASSERT_TRUE(back) << back.error().message;
    EXPECT_EQ(cv::norm(back->image, image, cv::NORM_INF), 0.0);
}

INSTANTIATE_TEST_SUITE_P(Types, OmePyramid, ::testing::Values(CV_8UC1, CV_16UC1, CV_8UC3),
                         [](const auto& p) {
                             return p.param == CV_8UC1    ? std::string("Mono8")
                                    : p.param == CV_16UC1 ? std::string("Mono16")
                                                          : std::string("Bgr8");
                         });

TEST(OmePyramid, LevelSizesHalveUntilTheTopFits) {
    using S = std::vector<cv::Size>;
    EXPECT_EQ(core::tiffPyramidLevels({1024, 700}, 1024), S({{1024, 700}}));
    EXPECT_EQ(core::tiffPyramidLevels({1025, 3}, 1024), S({{1025, 3}, {513, 2}}));
    EXPECT_EQ(
        core::tiffPyramidLevels({30000, 20001}, 1024),
        S({{30000, 20001}, {15000, 10001}, {7500, 5001}, {3750, 2501}, {1875, 1251}, {938, 626}}));
}

TEST(OmePyramid, BigTiffWhenForcedOrPastTheThreshold) {
    testing_dir::ScratchDir dir("pyr");
    const cv::Mat image = sectionLike(CV_8UC1, 1500, 700);
    const auto magic = [](const fs::path& p) {
        std::ifstream in(p, std::ios::binary);
        std::array<unsigned char, 4> m{};
        in.read(reinterpret_cast<char*>(m.data()), 4);
        return int{m[2]};
    };
    OmeTiffLayout forced;
    forced.bigTiff = OmeTiffLayout::BigTiff::Always;
    OmeTiffLayout threshold; // Auto, but a threshold this image passes (1.4 MB of pixels)
    threshold.bigTiffAboveBytes = 1'000'000;
    OmeTiffLayout under; // Auto with the default threshold: classic
    for (const auto& [name, layout, big] :
         {std::tuple{"forced", forced, true}, std::tuple{"threshold", threshold, true},
          std::tuple{"under", under, false}}) {
        const fs::path file = dir.path() / (std::string(name) + ".ome.tif");
        ASSERT_TRUE(daemon::writeOmeTiffAtomic(file, image, pyramidInfo(), layout)) << name;
        EXPECT_EQ(magic(file), big ? 43 : 42) << name; // TIFF 6.0: 42; BigTIFF: 43
        auto info = core::readTiffPyramidInfo(file);
        ASSERT_TRUE(info) << info.error().message;
        EXPECT_EQ(info->bigTiff, big) << name;
        ASSERT_EQ(info->levels.size(), 2u) << name;
        EXPECT_EQ(info->levels[1], cv::Size(750, 350));
        auto back = daemon::readOmeTiff(file);
        ASSERT_TRUE(back) << back.error().message;
        EXPECT_EQ(cv::norm(back->image, image, cv::NORM_INF), 0.0) << name;
        cv::Mat reference;
        cv::resize(image, reference, {750, 350}, 0, 0, cv::INTER_AREA);
        EXPECT_EQ(
            cv::norm(assembleLevel(file, 1, {750, 350}, 512, CV_8UC1), reference, cv::NORM_INF),
            0.0)
            << name;
    }
}

TEST(OmePyramid, TileReadsOutsideTheFileAreErrors) {
    testing_dir::ScratchDir dir("pyr");
    const fs::path file = dir.path() / "t.ome.tif";
    ASSERT_TRUE(daemon::writeOmeTiffAtomic(file, sectionLike(CV_8UC1, 1100, 600), pyramidInfo()));
    auto edge = core::readTiffTile(file, 0, 2, 1); // the last tile: 76 x 88 px
    ASSERT_TRUE(edge) << edge.error().message;
    EXPECT_EQ(edge->size(), cv::Size(1100 - 1024, 600 - 512));
    for (const auto& [level, x, y] :
         {std::tuple{2, 0, 0}, std::tuple{-1, 0, 0}, std::tuple{0, 3, 0}, std::tuple{0, 0, 2},
          std::tuple{1, 2, 0}, std::tuple{0, -1, 0}}) {
        auto t = core::readTiffTile(file, level, x, y);
        ASSERT_FALSE(t) << level << " " << x << " " << y;
        EXPECT_EQ(t.error().code, ErrorCode::NotFound) << t.error().message;
    }
    auto missing = core::readTiffTile(dir.path() / "none.tif", 0, 0, 0);
    ASSERT_FALSE(missing);
    EXPECT_EQ(missing.error().code, ErrorCode::NotFound);
    // A stripped TIFF has no tiles to serve.
    const fs::path plain = dir.path() / "plain.tif";
    ASSERT_TRUE(core::writeImage(plain, sectionLike(CV_8UC1, 64, 64)));
    auto stripped = core::readTiffTile(plain, 0, 0, 0);
    ASSERT_FALSE(stripped);
    EXPECT_EQ(stripped.error().code, ErrorCode::Unsupported);
    auto notTiff = dir.path() / "x.tif";
    std::ofstream(notTiff) << "not a tiff at all";
    auto garbage = core::readTiffTile(notTiff, 0, 0, 0);
    ASSERT_FALSE(garbage);
    EXPECT_EQ(garbage.error().code, ErrorCode::IoError);
}

TEST(OmePyramid, LayoutOutOfRangeIsRefused) {
    testing_dir::ScratchDir dir("pyr");
    for (const int tile : {0, 8, 100, 8192}) {
        OmeTiffLayout layout;
        layout.tileSizePx = tile;
        auto w = daemon::writeOmeTiffAtomic(dir.path() / "l.ome.tif", sectionLike(CV_8UC1, 32, 32),
                                            pyramidInfo(), layout);
        ASSERT_FALSE(w) << tile;
        EXPECT_EQ(w.error().code, ErrorCode::InvalidArgument) << w.error().message;
        EXPECT_TRUE(fs::is_empty(dir.path())) << tile;
    }
}

// The OME schema (2016-06) rules Bio-Formats checks or relies on, as an XSD would state them:
// IDs of the form "Kind:n", enumerations, positive numbers, Color as xsd:int, SizeC equal to
// the channels' samples, element order within Instrument, Image and Pixels, and references that
// resolve.
TEST(OmePyramid, OmeXmlFollowsTheSchemaRulesBioFormatsUses) {
    OmeTiffInfo info = pyramidInfo();
    info.channelRgba = 0xFF0000FFu; // red: negative as a signed int
    for (const int type : {CV_8UC1, CV_16UC1, CV_8UC3}) {
        const std::string xml = daemon::makeOmeXml(2600, 1900, type, info);
        pugi::xml_document doc;
        ASSERT_TRUE(doc.load_string(xml.c_str()));
        const pugi::xml_node ome = doc.child("OME");
        ASSERT_TRUE(ome);
        EXPECT_EQ(std::string(ome.attribute("Creator").value()),
                  std::string("slicestation ") + daemon::kVersion);
        const std::regex uuid("urn:uuid:[0-9a-f]{8}-[0-9a-f]{4}-4[0-9a-f]{3}-[89ab][0-9a-f]{3}-"
                              "[0-9a-f]{12}");
        EXPECT_TRUE(std::regex_match(ome.attribute("UUID").value(), uuid));

        const pugi::xml_node instrument = ome.child("Instrument");
        const std::vector<std::string> instrumentOrder = {"Detector", "Objective"};
        std::vector<std::string> seen;
        for (auto c : instrument.children())
            seen.push_back(c.name());
        EXPECT_EQ(seen, instrumentOrder);
        const pugi::xml_node objective = instrument.child("Objective");
        EXPECT_TRUE(std::regex_match(objective.attribute("ID").value(),
                                     std::regex(R"(Objective:\S+(:\S+)?)")));
        EXPECT_EQ(std::string(objective.attribute("Model").value()), "4x");
        EXPECT_EQ(objective.attribute("NominalMagnification").as_double(), 4.0);

        const pugi::xml_node image = ome.child("Image");
        EXPECT_TRUE(std::regex_match(image.attribute("ID").value(), std::regex(R"(Image:\S+)")));
        seen.clear();
        for (auto c : image.children())
            seen.push_back(c.name());
        const std::vector<std::string> imageOrder = {"AcquisitionDate", "InstrumentRef",
                                                     "ObjectiveSettings", "StageLabel", "Pixels"};
        EXPECT_EQ(seen, imageOrder);
        EXPECT_EQ(std::string(image.child("InstrumentRef").attribute("ID").value()),
                  instrument.attribute("ID").value());
        EXPECT_EQ(std::string(image.child("ObjectiveSettings").attribute("ID").value()),
                  objective.attribute("ID").value());
        const pugi::xml_node label = image.child("StageLabel");
        EXPECT_EQ(std::string(label.attribute("Name").value()), "image centre");
        EXPECT_EQ(label.attribute("X").as_double(), 40'000);
        EXPECT_EQ(label.attribute("Y").as_double(), 21'500.5);

        const pugi::xml_node pixels = image.child("Pixels");
        EXPECT_TRUE(std::regex_match(pixels.attribute("ID").value(), std::regex(R"(Pixels:\S+)")));
        EXPECT_TRUE(std::regex_match(pixels.attribute("DimensionOrder").value(),
                                     std::regex("XY(ZCT|ZTC|CTZ|CZT|TCZ|TZC)")));
        EXPECT_TRUE(std::regex_match(
            pixels.attribute("Type").value(),
            std::regex("int8|int16|int32|uint8|uint16|uint32|float|double|bit|complex|"
                       "double-complex")));
        for (const char* key : {"SizeX", "SizeY", "SizeZ", "SizeC", "SizeT"})
            EXPECT_GE(pixels.attribute(key).as_int(), 1) << key; // PositiveInt
        EXPECT_EQ(pixels.attribute("SizeX").as_int(), 2600);
        EXPECT_GT(pixels.attribute("PhysicalSizeX").as_double(), 0); // PositiveFloat
        EXPECT_GT(pixels.attribute("PhysicalSizeY").as_double(), 0);
        seen.clear();
        int samples = 0;
        int channels = 0;
        for (auto c : pixels.children()) {
            seen.push_back(c.name());
            if (std::string(c.name()) != "Channel")
                continue;
            ++channels;
            samples += c.attribute("SamplesPerPixel").as_int(1);
            EXPECT_TRUE(
                std::regex_match(c.attribute("ID").value(), std::regex(R"(Channel:\S+(:\S+)?)")));
            // Color: xsd:int, the RGBA bytes as a signed 32-bit number (OME's Color type).
            const std::string color = c.attribute("Color").value();
            EXPECT_TRUE(std::regex_match(color, std::regex(R"(-?[0-9]+)"))) << color;
            EXPECT_EQ(std::stoll(color), static_cast<std::int32_t>(0xFF0000FFu));
        }
        const std::vector<std::string> pixelsOrder = {"Channel", "TiffData", "Plane"};
        EXPECT_EQ(seen, pixelsOrder);
        EXPECT_EQ(samples, pixels.attribute("SizeC").as_int()) << "SizeC = samples of channels";
        // One IFD holds SizeZ * SizeT * channels planes' worth of TiffData (PlaneCount).
        const pugi::xml_node tiffData = pixels.child("TiffData");
        EXPECT_EQ(tiffData.attribute("PlaneCount").as_int(),
                  pixels.attribute("SizeZ").as_int() * pixels.attribute("SizeT").as_int() *
                      channels);
        EXPECT_EQ(tiffData.attribute("IFD").as_int(), 0);
        const pugi::xml_node plane = pixels.child("Plane");
        EXPECT_EQ(plane.attribute("PositionX").as_double(), 40'000);
        EXPECT_EQ(std::string(plane.attribute("PositionXUnit").value()), "µm");
    }
}

TEST(OmePyramid, ObjectiveColourAndVersionComeBack) {
    testing_dir::ScratchDir dir("pyr");
    const fs::path file = dir.path() / "m.ome.tif";
    OmeTiffInfo info = pyramidInfo();
    info.channelRgba = 0xFF0000FFu;
    info.objective = "10X Plan Apo";
    ASSERT_TRUE(daemon::writeOmeTiffAtomic(file, sectionLike(CV_16UC1, 100, 80), info));
    auto back = daemon::readOmeTiff(file);
    ASSERT_TRUE(back) << back.error().message;
    EXPECT_EQ(back->info.objective, "10X Plan Apo");
    EXPECT_EQ(back->info.channelRgba, 0xFF0000FFu);
    TIFF* tif = TIFFOpen(file.c_str(), "r");
    ASSERT_NE(tif, nullptr);
    const char* software = nullptr;
    TIFFGetField(tif, TIFFTAG_SOFTWARE, &software);
    EXPECT_EQ(std::string(software ? software : ""),
              std::string("slicestation ") + daemon::kVersion);
    TIFFClose(tif);
    // A name that states no magnification has no NominalMagnification.
    info.objective = "custom";
    EXPECT_EQ(daemon::makeOmeXml(4, 4, CV_8UC1, info).find("NominalMagnification"),
              std::string::npos);
    // Color must be a 32-bit integer.
    std::string xml = daemon::makeOmeXml(4, 4, CV_8UC1, pyramidInfo());
    xml.replace(xml.find("Color=\"") + 7,
                xml.find('"', xml.find("Color=\"") + 7) - (xml.find("Color=\"") + 7), "4294967295");
    auto parsed = daemon::parseOmeXml(xml);
    ASSERT_FALSE(parsed);
    EXPECT_NE(parsed.error().message.find("Color"), std::string::npos) << parsed.error().message;
}

} // namespace
} // namespace slicestation::test
