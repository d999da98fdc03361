// slicectl register, end to end through the real binary and real files.
#include "slicestation/core/image_file.hpp"
#include "slicestation/sim/builtin_atlas.hpp"
#include "slicestation/sim/section_generator.hpp"

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <nlohmann/json.hpp>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <sys/wait.h>
#include <unistd.h>

using namespace slicestation;
namespace fs = std::filesystem;

namespace {

struct CommandResult {
    int exitCode = -1;
    std::string output;
};

CommandResult slicectl(const std::string& args) {
    CommandResult r;
    const std::string cmd = std::string(SLICECTL_PATH) + " " + args + " 2>&1";
    FILE* p = ::popen(cmd.c_str(), "r");
    std::array<char, 4096> buf{};
    while (p && std::fgets(buf.data(), buf.size(), p)) r.output += buf.data();
    const int status = p ? ::pclose(p) : -1;
    r.exitCode = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
    return r;
}

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
        for (const auto& l : truth_) pts << l.image.x << "," << l.image.y << "\n";
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
    const CommandResult r = slicectl("register --atlas " + p("atlas.tif") + " --image " + p("section.tif") +
                           " --points " + p("points.csv") + " --output " + p("result.json") +
                           " --overlay " + p("overlay.png") + " --warped-labels " + p("warped.tif"));
    ASSERT_EQ(r.exitCode, 0) << r.output;
    std::ifstream in(p("result.json"));
    const auto j = nlohmann::json::parse(in);
    EXPECT_EQ(j.at("damaged"), false);
    EXPECT_TRUE(j.at("damage_regions").is_array());
    ASSERT_EQ(j.at("affine_atlas_from_image").size(), 2u);
    EXPECT_EQ(j.at("affine_atlas_from_image")[0].size(), 3u);
    EXPECT_TRUE(j.at("quality").contains("correspondences"));
    EXPECT_GT(j.at("timings_ms").at("total").get<double>(), 0.0);
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
    const fs::path dir = fs::temp_directory_path() / ("slst_slicectl_station_" + std::to_string(::getpid()));
    fs::create_directories(dir);
    const auto write = [&](const std::string& name, const std::string& text) {
        std::ofstream(dir / name, std::ios::binary) << text;
        return (dir / name).string();
    };
    const std::string stage = "[stage]\ndriver = \"sim\"\n[stage.axes.x]\nmin_um = 0\nmax_um = 75000\n"
                              "[stage.axes.y]\nmin_um = 0\nmax_um = 25000\n";
    auto r = slicectl("status --config " + write("tokn.toml", stage + "[daemon]\ntokn = \"0123456789abcdef\"\n[scan]\num_per_px = 2\n"));
    EXPECT_EQ(r.exitCode, 2) << r.output;
    EXPECT_NE(r.output.find("daemon: unknown key \"tokn\"; did you mean \"token\"?"), std::string::npos) << r.output;
    std::string dotted = "a";
    for (int i = 0; i < 200'000; ++i) dotted += ".a";
    r = slicectl("status --config " + write("deep.toml", stage + dotted + " = 1\n"));
    EXPECT_EQ(r.exitCode, 2) << r.output.substr(0, 300);
    EXPECT_NE(r.output.find("nested deeper than 64 levels"), std::string::npos) << r.output.substr(0, 300);
    r = slicectl("stage --config " + write("speed.toml", "[stage]\ndriver = \"sim\"\nspeeed_um_per_s = 5\n"
                                                                  "[stage.axes.x]\nmin_um = 0\nmax_um = 1\n"
                                                                  "[stage.axes.y]\nmin_um = 0\nmax_um = 1\n") + " position");
    EXPECT_EQ(r.exitCode, 2) << r.output;
    EXPECT_NE(r.output.find("did you mean \"speed_um_per_s\"?"), std::string::npos) << r.output;
    fs::remove_all(dir);
}
