// [camera] station configuration, openCamera, and slicectl camera capture through the binary.
#include "../common/run_command.hpp"
#include "slicestation/core/image_file.hpp"
#include "slicestation/daemon/config/station_config.hpp"
#include "slicestation/daemon/devices/devices.hpp"

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include <filesystem>
#include <fstream>

namespace slicestation::test {
namespace {

using namespace std::chrono_literals;
using core::ErrorCode;

using testing_cli::slicectl;

nlohmann::json jsonIn(const std::string& out) {
    const auto pos = out.find('{');
    return nlohmann::json::parse(out.substr(pos == std::string::npos ? 0 : pos), nullptr, false);
}

const std::filesystem::path& dir() {
    static const auto d = [] {
        auto p = std::filesystem::path(SLST_BINARY_DIR) / "tests_hw_tmp" / "camera";
        std::filesystem::create_directories(p);
        return p;
    }();
    return d;
}

std::filesystem::path writeFile(const std::string& name, const std::string& text) {
    const auto f = dir() / name;
    std::ofstream(f) << text;
    return f;
}

const std::string kStage = "[stage]\ndriver = \"sim\"\nsettle_ms = 0\nspeed_um_per_s = "
                           "1000000\naccel_um_per_s2 = 10000000\n"
                           "[stage.axes.x]\nmin_um = 0\nmax_um = 75000\n"
                           "[stage.axes.y]\nmin_um = 0\nmax_um = 25000\n"
                           "[stage.axes.z]\nmin_um = 0\nmax_um = 5000\n";

// One small generated section at (1000 + 200 + 1200, 500 + 200 + 1200) = (2400, 1900) µm.
const std::string kSimCamera =
    "[camera]\ndriver = \"sim\"\nformat = \"mono16\"\nwidth = 320\nheight = 240\n"
    "exposure_us = 20000\ngain = 2.0\ncapture_timeout_s = 2\n"
    "[camera.sim]\nsensor_um_per_px = 4.0\nfocus_z_um = 0\nslide_um_per_px = 8\n"
    "slide_origin_x_um = 1000\nslide_origin_y_um = 500\nsection_pitch_um = 2400\n"
    "section_width_um = 2400\nmargin_um = 200\ncolumns = 1\n"
    "[[camera.sim.sections]]\nap_fraction = 0.5\ndamage = \"tear\"\nseed = 3\n";

core::Result<daemon::StationConfig> parse(const std::string& toml) {
    return daemon::parseStationConfig(toml, dir() / "station.toml");
}

TEST(CameraConfig, StageOnlyFilesStillParse) {
    auto c = parse(kStage);
    ASSERT_TRUE(c) << c.error().message;
    EXPECT_TRUE(c->camera.driver.empty());
    bool simulated = true;
    auto cam = daemon::openCamera(
        c->camera, [] { return hw::StagePosition{}; }, simulated);
    ASSERT_FALSE(cam);
    EXPECT_EQ(cam.error().code, ErrorCode::InvalidArgument);
    EXPECT_NE(cam.error().message.find("[camera]"), std::string::npos);
}

TEST(CameraConfig, EveryKeyIsRead) {
    auto c = parse(kStage + kSimCamera);
    ASSERT_TRUE(c) << c.error().message;
    const auto& cc = c->camera;
    EXPECT_EQ(cc.driver, "sim");
    EXPECT_EQ(cc.settings.format, hw::PixelFormat::Mono16);
    EXPECT_EQ(cc.settings.width, 320);
    EXPECT_EQ(cc.settings.exposureUs, 20'000);
    EXPECT_DOUBLE_EQ(cc.settings.analogueGain, 2.0);
    EXPECT_EQ(cc.captureTimeout, 2s);
    EXPECT_DOUBLE_EQ(cc.sim.sensorUmPerPx, 4.0);
    ASSERT_EQ(cc.sim.slide.sections.size(), 1u);
    EXPECT_EQ(cc.sim.slide.sections[0].damage, "tear");
    EXPECT_EQ(cc.sim.slide.sections[0].seed, 3u);
    EXPECT_DOUBLE_EQ(cc.sim.slide.originXUm, 1000);

    auto v = parse(kStage + "[camera]\ndriver = \"v4l2\"\ndevice = \"/dev/video7\"\nformat = "
                            "\"rgb8\"\nred_gain = 1.5\nsettle_frames = 5\n");
    ASSERT_TRUE(v) << v.error().message;
    EXPECT_EQ(v->camera.device, "/dev/video7");
    EXPECT_DOUBLE_EQ(v->camera.settings.redGain, 1.5);
    EXPECT_EQ(v->camera.settleFrames, 5);
    auto l = parse(kStage + "[camera]\ndriver = \"libcamera\"\ncamera_id = \"imx477\"\n");
    ASSERT_TRUE(l);
    EXPECT_EQ(l->camera.cameraId, "imx477");
    auto d = parse(kStage + "[camera]\ndriver = \"sim\"\n"); // default slide: four sections
    ASSERT_TRUE(d);
    EXPECT_EQ(d->camera.sim.slide.sections.size(), 4u);
}

TEST(CameraConfig, ErrorsNameTheKey) {
    const std::vector<std::pair<std::string, std::string>> cases{
        {"[camera]\ndriver = \"gphoto\"\n", "camera.driver"},
        {"[camera]\nwidth = 640\n", "camera.driver"},
        {"[camera]\ndriver = \"sim\"\nwidth = -5\n", "camera.width"},
        {"[camera]\ndriver = \"sim\"\nheight = 100.5\n", "camera.height"},
        {"[camera]\ndriver = \"sim\"\nformat = \"bayer\"\n", "camera.format"},
        {"[camera]\ndriver = \"sim\"\nexposure_us = 0\n", "camera.exposure_us"},
        {"[camera]\ndriver = \"sim\"\ngain = \"high\"\n", "camera.gain"},
        {"[camera]\ndriver = \"sim\"\ncapture_timeout_s = 0\n", "camera.capture_timeout_s"},
        {"[camera]\ndriver = \"v4l2\"\ndevice = 7\n", "camera.device"},
        {"[camera]\ndriver = \"v4l2\"\n[camera.sim]\ncolumns = 2\n", "camera.sim"},
        {"[camera]\ndriver = \"sim\"\n[camera.sim]\nsensor_um_per_px = 0\n",
         "camera.sim.sensor_um_per_px"},
        {"[camera]\ndriver = \"sim\"\n[camera.sim]\ncolumns = 0\n", "camera.sim.columns"},
        {"[camera]\ndriver = \"sim\"\n[camera.sim]\nsection_width_um = 20000\n",
         "camera.sim.section_width_um"},
        {"[camera]\ndriver = \"sim\"\n[camera.sim]\nbrightfield = 1\n", "camera.sim.brightfield"},
        {"[camera]\ndriver = \"sim\"\n[camera.sim]\nimages = []\n", "camera.sim.images"},
        {"[camera]\ndriver = \"sim\"\n[[camera.sim.sections]]\nap_fraction = "
         "0.5\n[[camera.sim.sections]]\nap_fraction = 0.5\ndamage = \"burnt\"\n",
         "camera.sim.sections[1].damage"},
        {"[camera]\ndriver = \"sim\"\n[[camera.sim.sections]]\nap_fraction = 1.5\n",
         "camera.sim.sections[0].ap_fraction"},
        {"[camera]\ndriver = \"sim\"\n[[camera.sim.sections]]\ndamage = \"tear\"\n",
         "camera.sim.sections[0].ap_fraction"},
    };
    for (const auto& [toml, key] : cases) {
        auto c = parse(kStage + toml);
        ASSERT_FALSE(c) << toml;
        EXPECT_EQ(c.error().code, ErrorCode::InvalidArgument);
        EXPECT_NE(c.error().message.find(key), std::string::npos)
            << "want " << key << " in: " << c.error().message;
    }
    auto c = parse("camera = 3\n" + kStage);
    ASSERT_FALSE(c);
    EXPECT_NE(c.error().message.find("camera: expected a table"), std::string::npos)
        << c.error().message;
}

TEST(OpenCamera, SimLooksWhereTheStagePositionSays) {
    auto c = parse(kStage + kSimCamera);
    ASSERT_TRUE(c);
    hw::StagePosition where{2400, 1900, 0}; // the section centre
    bool simulated = false;
    auto cam = daemon::openCamera(
        c->camera, [&where] { return where; }, simulated);
    ASSERT_TRUE(cam) << cam.error().message;
    EXPECT_TRUE(simulated);
    ASSERT_TRUE((*cam)->configure(c->camera.settings, 1s));
    auto tissue = (*cam)->capture(1s).value();
    where = {1100, 600, 0}; // the slide's corner: glass
    auto glass = (*cam)->capture(1s).value();
    auto mean = [](const hw::Frame& f) {
        double s = 0;
        for (std::size_t i = 0; i + 1 < f.bytes().size(); i += 2)
            s += f.bytes()[i + 1]; // high bytes
        return s / (f.bytes().size() / 2.0);
    };
    EXPECT_GT(mean(tissue), mean(glass) + 10);
    EXPECT_DOUBLE_EQ(tissue.metadata.stage->xUm, 2400);
}

TEST(OpenCamera, SimFaultsFromTheConfig) {
    std::string toml = kSimCamera;
    toml.insert(toml.find("[[camera.sim.sections]]"), "disconnect_after_frames = 1\n");
    auto c = parse(kStage + toml);
    ASSERT_TRUE(c) << c.error().message;
    bool simulated = false;
    auto cam = daemon::openCamera(
        c->camera, [] { return hw::StagePosition{}; }, simulated);
    ASSERT_TRUE(cam);
    EXPECT_TRUE((*cam)->capture(1s));
    EXPECT_EQ((*cam)->capture(1s).error().code, ErrorCode::Disconnected);
}

TEST(OpenCamera, DriverErrorsPassThrough) {
    bool simulated = true;
    auto v = parse(kStage + "[camera]\ndriver = \"v4l2\"\ndevice = \"/dev/video-none-here\"\n");
    ASSERT_TRUE(v);
    auto cam = daemon::openCamera(v->camera, nullptr, simulated);
    ASSERT_FALSE(cam);
    EXPECT_FALSE(simulated);
    EXPECT_EQ(cam.error().code, ErrorCode::NotFound);
    EXPECT_NE(cam.error().message.find("/dev/video-none-here"), std::string::npos);
    auto s = parse(kStage + kSimCamera);
    EXPECT_EQ(daemon::openCamera(s->camera, nullptr, simulated).error().code,
              ErrorCode::InvalidArgument);
    auto i =
        parse(kStage + "[camera]\ndriver = \"sim\"\n[camera.sim]\nimages = [\"missing.tif\"]\n");
    ASSERT_TRUE(i) << i.error().message;
    auto m = daemon::openCamera(
        i->camera, [] { return hw::StagePosition{}; }, simulated);
    ASSERT_FALSE(m);
    EXPECT_EQ(m.error().code, ErrorCode::NotFound);
    EXPECT_NE(m.error().message.find("camera.sim"), std::string::npos);
}

TEST(OpenCamera, RealSectionImagesAsTheSlide) {
    const auto f = std::filesystem::path(SLST_SHARED_DIR) / "sections" / "abba-mouse-series" /
                   "Section-08.tif";
    if (!std::filesystem::exists(f))
        GTEST_SKIP() << "no ../shared/sections";
    auto c =
        parse(kStage +
              "[camera]\ndriver = \"sim\"\nwidth = 256\nheight = 256\n[camera.sim]\nimages = [\"" +
              f.string() +
              "\"]\nimages_um_per_px = 20\nsection_pitch_um = 14000\nslide_origin_x_um = "
              "3000\nslide_origin_y_um = 3000\n"
              "sensor_um_per_px = 20\nfocus_z_um = 0\n");
    ASSERT_TRUE(c) << c.error().message;
    bool simulated = false;
    auto cam = daemon::openCamera(
        c->camera,
        [] {
            return hw::StagePosition{10'000, 10'000, 0};
        },
        simulated);
    ASSERT_TRUE(cam) << cam.error().message;
    ASSERT_TRUE((*cam)->configure(c->camera.settings, 1s));
    EXPECT_TRUE((*cam)->capture(1s));
}

// ---- through the binary ---------------------------------------------------------------------

TEST(SlicectlCamera, CaptureWritesALosslessTiffAndPrintsJson) {
    const auto cfg = writeFile("sim_camera.toml", kStage + kSimCamera);
    const auto out = dir() / "frame.tif";
    std::filesystem::remove(out);
    auto r = slicectl("camera --config " + cfg.string() + " capture --output " + out.string() +
                      " --x-um 2400 --y-um 1900 --z-um 0");
    ASSERT_EQ(r.exitCode, 0) << r.output;
    EXPECT_NE(r.output.find("SIMULATED camera"), std::string::npos);
    auto j = jsonIn(r.output);
    ASSERT_FALSE(j.is_discarded()) << r.output;
    EXPECT_EQ(j["settings_used"]["width"], 320);
    EXPECT_EQ(j["settings_requested"]["exposure_us"], 20000);
    EXPECT_EQ(j["frame"]["format"], "mono16");
    EXPECT_EQ(j["frame"]["exposure_us"], 20000);
    EXPECT_DOUBLE_EQ(j["frame"]["stage"]["x_um"].get<double>(), 2400);
    EXPECT_TRUE(j["simulated"].get<bool>());
    auto img = core::readImage(out);
    ASSERT_TRUE(img) << img.error().message;
    EXPECT_EQ(img->type(), CV_16UC1);
    EXPECT_EQ(img->cols, 320);
    EXPECT_EQ(img->rows, 240);
}

TEST(SlicectlCamera, RgbFramesAndPng) {
    std::string toml = kSimCamera;
    toml.replace(toml.find("mono16"), 6, "rgb8");
    const auto cfg = writeFile("sim_camera_rgb.toml", kStage + toml);
    const auto out = dir() / "frame.png";
    auto r = slicectl("camera --config " + cfg.string() + " capture --output " + out.string());
    ASSERT_EQ(r.exitCode, 0) << r.output;
    auto img = core::readImage(out);
    ASSERT_TRUE(img);
    EXPECT_EQ(img->type(), CV_8UC3);
}

TEST(SlicectlCamera, BadInputsExitNonZeroWithTheReason) {
    const auto noCamera = writeFile("stage_only.toml", kStage);
    auto r = slicectl("camera --config " + noCamera.string() + " capture --output " +
                      (dir() / "x.tif").string());
    EXPECT_EQ(r.exitCode, 2);
    EXPECT_NE(r.output.find("[camera]"), std::string::npos) << r.output;

    const auto badWidth =
        writeFile("bad_width.toml", kStage + "[camera]\ndriver = \"sim\"\nwidth = -5\n");
    r = slicectl("camera --config " + badWidth.string() + " capture --output " +
                 (dir() / "x.tif").string());
    EXPECT_EQ(r.exitCode, 2);
    EXPECT_NE(r.output.find("camera.width"), std::string::npos) << r.output;

    const auto v4l2 =
        writeFile("v4l2_missing.toml",
                  kStage + "[camera]\ndriver = \"v4l2\"\ndevice = \"/dev/video-none-here\"\n");
    r = slicectl("camera --config " + v4l2.string() + " capture --output " +
                 (dir() / "x.tif").string());
    EXPECT_NE(r.exitCode, 0);
    EXPECT_NE(r.output.find("/dev/video-none-here"), std::string::npos) << r.output;

    const auto libcam = writeFile("libcamera.toml", kStage + "[camera]\ndriver = \"libcamera\"\n");
    r = slicectl("camera --config " + libcam.string() + " capture --output " +
                 (dir() / "x.tif").string());
    EXPECT_NE(r.exitCode, 0);
    EXPECT_NE(r.output.find("no camera found"), std::string::npos) << r.output;

    const auto sim = writeFile("sim_ok.toml", kStage + kSimCamera);
    r = slicectl("camera --config " + sim.string() + " capture --output " +
                 (dir() / "frame.jpg").string());
    EXPECT_EQ(r.exitCode, 2);
    EXPECT_NE(r.output.find("lossless"), std::string::npos) << r.output;
    r = slicectl("camera --config " + sim.string() +
                 " capture --output /nonexistent-dir/frame.tif");
    EXPECT_NE(r.exitCode, 0);
    r = slicectl("camera --config " + sim.string() + " capture --output " +
                 (dir() / "y.tif").string() + " --x-um 999999 --y-um 0");
    EXPECT_EQ(r.exitCode, 2);
    EXPECT_NE(r.output.find("soft limits"), std::string::npos) << r.output;
    r = slicectl("camera --config " + (dir() / "missing.toml").string() +
                 " capture --output x.tif");
    EXPECT_NE(r.exitCode, 0);
}

} // namespace
} // namespace slicestation::test
