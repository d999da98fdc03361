// Configuration to devices: the driver registry opens what a station file names, says when it
// is a simulator, and refuses a camera it has no driver for.
#include "slicestation/daemon/devices/devices.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>

using namespace slicestation;
using namespace slicestation::daemon;

namespace {

constexpr const char* kSimStation = R"(
[stage]
driver = "sim"
[stage.axes.x]
min_um = 0
max_um = 75000
[stage.axes.y]
min_um = 0
max_um = 25000
[stage.axes.z]
min_um = 0
max_um = 5000
[camera]
driver = "sim"
width = 320
height = 240
)";

TEST(Devices, TheRegistryOpensASimulatedStationAndSaysSo) {
    auto cfg = parseStationConfig(kSimStation, "station.toml");
    ASSERT_TRUE(cfg) << cfg.error().message;
    bool stageSimulated = false, cameraSimulated = false;
    auto stage = openStage(cfg->stage, stageSimulated);
    ASSERT_TRUE(stage) << stage.error().message;
    EXPECT_TRUE(stageSimulated);
    EXPECT_TRUE((*stage)->limits().z);
    auto camera = openCamera(
        cfg->camera, [] { return hw::StagePosition{}; }, cameraSimulated);
    ASSERT_TRUE(camera) << camera.error().message;
    EXPECT_TRUE(cameraSimulated);
    auto used = (*camera)->configure(cfg->camera.settings, std::chrono::seconds(1));
    ASSERT_TRUE(used) << used.error().message;
    EXPECT_EQ(used->width, 320);
}

TEST(Devices, ACameraWithoutDriverOrStagePositionIsRefused) {
    auto cfg = parseStationConfig(kSimStation, "station.toml");
    ASSERT_TRUE(cfg);
    bool simulated = true;
    CameraConfig none;
    auto missing = openCamera(
        none, [] { return hw::StagePosition{}; }, simulated);
    ASSERT_FALSE(missing);
    EXPECT_EQ(missing.error().code, core::ErrorCode::InvalidArgument);
    EXPECT_NE(missing.error().message.find("no [camera] section"), std::string::npos);

    CameraConfig unknown = cfg->camera;
    unknown.driver = "gige";
    auto refused = openCamera(
        unknown, [] { return hw::StagePosition{}; }, simulated);
    ASSERT_FALSE(refused);
    EXPECT_NE(refused.error().message.find("no driver \"gige\" (known: v4l2, libcamera, sim)"),
              std::string::npos)
        << refused.error().message;

    auto blind = openCamera(cfg->camera, {}, simulated);
    ASSERT_FALSE(blind) << "a simulated camera must know where the stage is";
    EXPECT_EQ(blind.error().code, core::ErrorCode::InvalidArgument);
}

TEST(Devices, EveryDriverTheConfigurationAcceptsIsRegistered) {
    const auto cameras = cameraDriverNames();
    for (const char* name : {"v4l2", "libcamera", "sim"})
        EXPECT_NE(std::find(cameras.begin(), cameras.end(), name), cameras.end()) << name;
    const auto stages = stageDriverNames();
    EXPECT_EQ(stages, (std::vector<std::string>{"modbus", "sim"}));
}

} // namespace

TEST(Devices, AStageDriverTheRegistryLacksIsRefusedListingTheKnownOnes) {
    auto cfg = parseStationConfig(kSimStation, "station.toml");
    ASSERT_TRUE(cfg);
    StageConfig unknown = cfg->stage;
    unknown.driver = "canopen";
    bool simulated = true;
    auto refused = openStage(unknown, simulated);
    ASSERT_FALSE(refused);
    EXPECT_EQ(refused.error().code, core::ErrorCode::InvalidArgument);
    EXPECT_FALSE(simulated) << "an unknown driver is no simulator";
    EXPECT_NE(
        refused.error().message.find("stage.driver: no driver \"canopen\" (known: modbus, sim)"),
        std::string::npos)
        << refused.error().message;
}
