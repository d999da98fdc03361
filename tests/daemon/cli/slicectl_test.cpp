// slicectl register, end to end through the real binary and real files.
#include "../../common/run_command.hpp"
#include "slicestation/core/image_file.hpp"
#include "slicestation/sim/builtin_atlas.hpp"
#include "slicestation/sim/section_generator.hpp"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <tiffio.h>
#include <zlib.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <limits>
#include <sstream>
#include <unistd.h>

using namespace slicestation;
namespace fs = std::filesystem;

namespace {

using testing_cli::CommandResult;
using testing_cli::slicectl;

class SlicectlRegister : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = fs::temp_directory_path() / ("slst_slicectl_" + std::to_string(::getpid()));
        fs::create_directories(dir_);
        const cv::Mat atlas = sim::builtinAtlasPlane(0.5);
        sim::GeneratorOptions o;
        o.seed = 42;
        o.imageSize = {1200, 880};
        auto gen = sim::generateSection(atlas, o);
        ASSERT_TRUE(gen.ok()) << gen.error().message;
        truth_ = gen->truth.landmarks;
        ASSERT_TRUE(core::writeImage(dir_ / "atlas.tif", atlas).ok());
        ASSERT_TRUE(core::writeImage(dir_ / "section.tif", gen->image).ok());
        std::ofstream pts(dir_ / "points.csv");
        pts << "x,y\n";
        for (const auto& l : truth_)
            pts << l.image.x << "," << l.image.y << "\n";
    }
    static void TearDownTestSuite() { fs::remove_all(dir_); }
    static std::string p(const std::string& name) { return (dir_ / name).string(); }

    static fs::path dir_;
    static std::vector<sim::Landmark> truth_;
};
fs::path SlicectlRegister::dir_;
std::vector<sim::Landmark> SlicectlRegister::truth_;

} // namespace

TEST_F(SlicectlRegister, WritesTheResultContractAndMapsEveryPoint) {
    const CommandResult r =
        slicectl("register --atlas " + p("atlas.tif") + " --image " + p("section.tif") +
                 " --points " + p("points.csv") + " --output " + p("result.json") + " --overlay " +
                 p("overlay.png") + " --warped-labels " + p("warped.tif"));
    ASSERT_EQ(r.exitCode, 0) << r.output;
    std::ifstream in(p("result.json"));
    const auto j = nlohmann::json::parse(in);
    EXPECT_EQ(j.at("damaged"), false);
    EXPECT_TRUE(j.at("damage_regions").is_array());
    ASSERT_EQ(j.at("affine_atlas_from_image").size(), 2u);
    EXPECT_EQ(j.at("affine_atlas_from_image")[0].size(), 3u);
    EXPECT_TRUE(j.at("quality").contains("correspondences"));
    EXPECT_GT(j.at("timings_ms").at("total").get<double>(), 0.0);
    // Process CPU time: the whole process includes the call, the call its steps.
    const auto& cpu = j.at("cpu_timings_ms");
    EXPECT_GE(cpu.at("process").get<double>(), cpu.at("total").get<double>());
    EXPECT_GE(cpu.at("total").get<double>(), cpu.at("register").get<double>());
    EXPECT_GT(cpu.at("register").get<double>(), 0.0);
    const auto& pts = j.at("points");
    ASSERT_EQ(pts.size(), truth_.size());
    double ss = 0;
    for (size_t i = 0; i < truth_.size(); ++i) {
        EXPECT_DOUBLE_EQ(pts[i].at("x").get<double>(), truth_[i].image.x);
        ss += std::pow(pts[i].at("atlas_x").get<double>() - truth_[i].atlas.x, 2) +
              std::pow(pts[i].at("atlas_y").get<double>() - truth_[i].atlas.y, 2);
    }
    EXPECT_LT(std::sqrt(ss / double(truth_.size())), 3.0); // atlas px, built-in atlas
    auto overlay = core::readImage(p("overlay.png"));
    ASSERT_TRUE(overlay.ok());
    EXPECT_EQ(overlay->channels(), 3);
    auto warped = core::readImage(p("warped.tif"));
    ASSERT_TRUE(warped.ok());
    EXPECT_EQ(warped->size(), cv::Size(1200, 880));
    EXPECT_EQ(warped->type(), CV_32S);
    EXPECT_GT(cv::countNonZero(*warped), 100000);
}

TEST_F(SlicectlRegister, OneThreadGivesTheSameResultAsOnePerCore) {
    // --threads 1 runs every step on the calling thread; the default (0) one thread per core.
    for (const char* t : {"1", "0"}) {
        const CommandResult r =
            slicectl("register --threads " + std::string(t) + " --atlas " + p("atlas.tif") +
                     " --image " + p("section.tif") + " --points " + p("points.csv") +
                     " --output " + p(std::string("threads") + t + ".json"));
        ASSERT_EQ(r.exitCode, 0) << r.output;
    }
    const auto read = [&](const char* name) {
        std::ifstream in(p(name));
        auto j = nlohmann::json::parse(in);
        j.erase("timings_ms");
        j.erase("cpu_timings_ms");
        j["mapping"].erase("field"); // its own file name
        return j;
    };
    const auto one = read("threads1.json"), all = read("threads0.json");
    EXPECT_EQ(one, all) << "one thread:\n" << one.dump(1).substr(0, 2000);
    EXPECT_GT(one.at("points").size(), 10u);
    EXPECT_NE(slicectl("register --threads -1 --atlas " + p("atlas.tif") + " --image " +
                       p("section.tif") + " --output " + p("threads-bad.json"))
                  .exitCode,
              0);
}

TEST_F(SlicectlRegister, InvalidInputFailsWithAMessageAndKeepsTheOldResult) {
    {
        std::ofstream(p("empty.tif"));
        std::ofstream(p("bad.csv")) << "x,y\n1,2\n3,oops\n";
        ASSERT_TRUE(core::writeImage(p("blank.png"), cv::Mat(400, 400, CV_8U, cv::Scalar(9))).ok());
        ASSERT_TRUE(core::writeImage(p("nolabels.png"), cv::Mat::zeros(50, 50, CV_8U)).ok());
        std::ofstream(p("old.json")) << "{\"kept\": true}\n";
    }
    struct Case {
        std::string atlas, image, extra, needle;
    };
    const std::vector<Case> cases{
        {p("missing.tif"), p("section.tif"), "", "missing.tif"},
        {p("atlas.tif"), p("missing.tif"), "", "missing.tif"},
        {p("atlas.tif"), p("empty.tif"), "", "empty.tif"},
        {p("atlas.tif"), p("blank.png"), "", "no tissue"},
        {p("nolabels.png"), p("section.tif"), "", "no labels"},
        {p("atlas.tif"), p("section.tif"), "--points " + p("bad.csv"), "line 3"},
        {p("atlas.tif"), p("section.tif"), "--points " + p("nope.csv"), "nope.csv"},
        {p("atlas.tif"), p("section.tif"), "--image-um-per-px 2", "both"},
    };
    for (const Case& c : cases) {
        const CommandResult r = slicectl("register --atlas " + c.atlas + " --image " + c.image +
                                         " --output " + p("old.json") + " " + c.extra);
        EXPECT_NE(r.exitCode, 0) << c.needle;
        EXPECT_NE(r.output.find(c.needle), std::string::npos) << r.output;
        // One line, prefixed with the command.
        EXPECT_EQ(std::count(r.output.begin(), r.output.end(), '\n'), 1) << r.output;
        std::ifstream old(p("old.json"));
        std::stringstream ss;
        ss << old.rdbuf();
        EXPECT_EQ(ss.str(), "{\"kept\": true}\n") << "result overwritten for " << c.needle;
    }
}

/// A deflate TIFF of about 24 KB claiming width x height px of 8 bits: one strip, whose data
/// inflates to 24 MB of zeros, written with libtiff as any writer could.
void writeDeflateBomb(const fs::path& path, std::uint32_t width, std::uint32_t height) {
    TIFF* tif = TIFFOpen(path.c_str(), "w");
    ASSERT_NE(tif, nullptr);
    TIFFSetField(tif, TIFFTAG_IMAGEWIDTH, width);
    TIFFSetField(tif, TIFFTAG_IMAGELENGTH, height);
    TIFFSetField(tif, TIFFTAG_BITSPERSAMPLE, 8);
    TIFFSetField(tif, TIFFTAG_SAMPLESPERPIXEL, 1);
    TIFFSetField(tif, TIFFTAG_PHOTOMETRIC, PHOTOMETRIC_MINISBLACK);
    TIFFSetField(tif, TIFFTAG_PLANARCONFIG, PLANARCONFIG_CONTIG);
    TIFFSetField(tif, TIFFTAG_COMPRESSION, COMPRESSION_ADOBE_DEFLATE);
    TIFFSetField(tif, TIFFTAG_ROWSPERSTRIP, height);
    const std::vector<Bytef> zeros(24u << 20, 0);
    uLongf size = compressBound(static_cast<uLong>(zeros.size()));
    std::vector<Bytef> packed(size);
    ASSERT_EQ(compress2(packed.data(), &size, zeros.data(), static_cast<uLong>(zeros.size()), 9),
              Z_OK);
    ASSERT_EQ(TIFFWriteRawStrip(tif, 0, packed.data(), static_cast<tmsize_t>(size)),
              static_cast<tmsize_t>(size));
    TIFFClose(tif);
}

TEST_F(SlicectlRegister, HostileImagesAndOptionsExitTwoWithOneLine) {
    writeDeflateBomb(dir_ / "bomb.tif", 100000, 100000);
    ASSERT_LT(fs::file_size(dir_ / "bomb.tif"), 64u << 10);
    // 299 px wide: the README's range is 300 to 8000.
    ASSERT_TRUE(core::writeImage(p("narrow.tif"), cv::Mat(400, 299, CV_8U, cv::Scalar(30))).ok());
    // An atlas of one label everywhere: no outline to register to.
    ASSERT_TRUE(core::writeImage(p("onelabel.tif"), cv::Mat(320, 456, CV_32S, cv::Scalar(5))).ok());
    cv::Mat nan(880, 1200, CV_32F, cv::Scalar(100.0f));
    nan.at<float>(3, 4) = std::numeric_limits<float>::quiet_NaN();
    ASSERT_TRUE(core::writeImage(p("nan.tif"), nan).ok());
    // A stack whose manifest has a string for a slice's height.
    fs::create_directories(dir_ / "badstack");
    ASSERT_TRUE(
        core::writeImage(dir_ / "badstack" / "slice-000.tif", sim::builtinAtlasPlane(0.5)).ok());
    std::ofstream(dir_ / "badstack" / "manifest.json")
        << R"({"slices": [{"index": 0, "file": "slice-000.tif", "position_um": 0,
              "normal": [1, 0, 0], "um_per_px": 25, "width": 456, "height": "x"}]})";
    struct Case {
        std::string atlas, image, extra, needle;
    };
    const std::vector<Case> cases{
        {p("atlas.tif"), p("bomb.tif"), "", "100000 x 100000"},
        {p("atlas.tif"), p("narrow.tif"), "", "300 to 8000 px"},
        {p("onelabel.tif"), p("section.tif"), "", "one label"},
        {p("atlas.tif"), p("nan.tif"), "", "nan.tif"},
        {p("badstack"), p("section.tif"), "--slice 0", "slices[0].height"},
        {p("atlas.tif"), p("section.tif"), "--image-um-per-px nan --atlas-um-per-px 25",
         "--image-um-per-px"},
        {p("atlas.tif"), p("section.tif"), "--image-um-per-px 2 --atlas-um-per-px inf",
         "--atlas-um-per-px"},
        {p("atlas.tif"), p("section.tif"), "--image-um-per-px 1e-6 --atlas-um-per-px 25",
         "--image-um-per-px"},
        {p("atlas.tif"), p("section.tif"), "--working-size 100000", "--working-size"},
        {p("atlas.tif"), p("section.tif"), "--max-turn 200", "--max-turn"},
    };
    for (const Case& c : cases) {
        const CommandResult r = slicectl("register --atlas " + c.atlas + " --image " + c.image +
                                         " --output " + p("hostile.json") + " " + c.extra);
        EXPECT_EQ(r.exitCode, 2) << c.needle << ": " << r.output;
        EXPECT_NE(r.output.find(c.needle), std::string::npos) << r.output;
        EXPECT_FALSE(fs::exists(p("hostile.json"))) << c.needle;
    }
}

TEST_F(SlicectlRegister, MissingRequiredOptionIsAUsageError) {
    const CommandResult r = slicectl("register --image " + p("section.tif"));
    EXPECT_NE(r.exitCode, 0);
    EXPECT_NE(r.output.find("--atlas"), std::string::npos) << r.output;
}

TEST(SlicectlDemo, RunsOnBuiltInDefaultsAndIsAccurate) {
    const fs::path out = fs::temp_directory_path() / ("slst_demo_" + std::to_string(::getpid()));
    const CommandResult r = slicectl("demo --output-dir " + out.string());
    ASSERT_EQ(r.exitCode, 0) << r.output;
    const auto j = nlohmann::json::parse(r.output);
    EXPECT_LT(j.at("rmse_atlas_px").get<double>(), 3.0);
    EXPECT_TRUE(fs::exists(out / "overlay.png"));
    EXPECT_TRUE(fs::exists(out / "result.json"));
    fs::remove_all(out);
}

// Issue 20: a misspelt or hostile station file is refused with exit 2 and a message naming the
// key, before slicectl talks to any daemon or device.
TEST(SlicectlStationFile, MisspeltAndHostileFilesAreRefusedWithExitTwo) {
    const fs::path dir =
        fs::temp_directory_path() / ("slst_slicectl_station_" + std::to_string(::getpid()));
    fs::create_directories(dir);
    const auto write = [&](const std::string& name, const std::string& text) {
        std::ofstream(dir / name, std::ios::binary) << text;
        return (dir / name).string();
    };
    const std::string stage =
        "[stage]\ndriver = \"sim\"\n[stage.axes.x]\nmin_um = 0\nmax_um = 75000\n"
        "[stage.axes.y]\nmin_um = 0\nmax_um = 25000\n";
    auto r =
        slicectl("status --config " +
                 write("tokn.toml",
                       stage + "[daemon]\ntokn = \"0123456789abcdef\"\n[scan]\num_per_px = 2\n"));
    EXPECT_EQ(r.exitCode, 2) << r.output;
    EXPECT_NE(r.output.find("daemon: unknown key \"tokn\"; did you mean \"token\"?"),
              std::string::npos)
        << r.output;
    std::string dotted = "a";
    for (int i = 0; i < 200'000; ++i)
        dotted += ".a";
    r = slicectl("status --config " + write("deep.toml", stage + dotted + " = 1\n"));
    EXPECT_EQ(r.exitCode, 2) << r.output.substr(0, 300);
    EXPECT_NE(r.output.find("nested deeper than 64 levels"), std::string::npos)
        << r.output.substr(0, 300);
    r = slicectl("stage --config " +
                 write("speed.toml", "[stage]\ndriver = \"sim\"\nspeeed_um_per_s = 5\n"
                                     "[stage.axes.x]\nmin_um = 0\nmax_um = 1\n"
                                     "[stage.axes.y]\nmin_um = 0\nmax_um = 1\n") +
                 " position");
    EXPECT_EQ(r.exitCode, 2) << r.output;
    EXPECT_NE(r.output.find("did you mean \"speed_um_per_s\"?"), std::string::npos) << r.output;
    fs::remove_all(dir);
}
