#include "slicestation/daemon/devices/devices.hpp"

#include "slicestation/drivers/libcamera_camera.hpp"
#include "slicestation/drivers/modbus_stage.hpp"
#include "slicestation/drivers/v4l2_camera.hpp"
#include "slicestation/sim/faulty_camera.hpp"
#include "slicestation/sim/sim_camera.hpp"
#include "slicestation/sim/sim_stage.hpp"
#include "slicestation/sim/virtual_slide.hpp"

#include <array>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;

namespace {

using StagePosition = std::function<hw::StagePosition()>;
using CameraResult = core::Result<std::unique_ptr<hw::Camera>>;
using StageResult = core::Result<std::unique_ptr<hw::Stage>>;

CameraResult openV4l2(const CameraConfig& config, StagePosition) {
    drivers::V4l2CameraConfig c;
    c.device = config.device;
    c.settleFrames = config.settleFrames;
    auto cam = drivers::V4l2Camera::create(c);
    if (!cam)
        return cam.error();
    return std::unique_ptr<hw::Camera>(std::move(cam).value());
}

CameraResult openLibcamera(const CameraConfig& config, StagePosition) {
    drivers::LibcameraCameraConfig c;
    c.cameraId = config.cameraId;
    c.settleFrames = config.settleFrames;
    return drivers::openLibcameraCamera(c); // loads the libcamera driver now
}

/// The simulated camera over its virtual slide, behind FaultyCamera when faults are asked.
CameraResult openSimCamera(const CameraConfig& config, StagePosition stagePosition) {
    if (!stagePosition)
        return makeError(ErrorCode::InvalidArgument,
                         "camera: the simulated camera needs the stage position");
    const auto& s = config.sim;
    auto slide = s.images.empty() ? sim::makeVirtualSlide(s.slide)
                                  : sim::loadVirtualSlide(s.images, s.imagesUmPerPx,
                                                          s.slide.columns, s.slide.sectionPitchUm);
    if (!slide)
        return makeError(slide.error().code, "camera.sim: " + slide.error().message,
                         slide.error().sysErrno);
    if (!s.images.empty()) { // loaded slides start at (0, 0); the configured origin moves them
        slide->originXUm = s.slide.originXUm;
        slide->originYUm = s.slide.originYUm;
        for (auto& sec : slide->sections) {
            sec.centre.xUm += s.slide.originXUm;
            sec.centre.yUm += s.slide.originYUm;
        }
    }
    sim::SimCameraConfig cc;
    cc.sensorUmPerPx = s.sensorUmPerPx;
    cc.stagePosition = std::move(stagePosition);
    cc.focusZUm = s.focusZUm;
    cc.focusTiltX = s.focusTiltX;
    cc.focusTiltY = s.focusTiltY;
    cc.blurSigmaPxPerUm = s.blurSigmaPxPerUm;
    auto cam = sim::SimCamera::create(*slide, std::move(cc));
    if (!cam)
        return cam.error();
    if (s.timeoutFirstCaptures == 0 && s.disconnectAfterFrames < 0)
        return std::unique_ptr<hw::Camera>(std::move(cam).value());
    auto faulty =
        sim::FaultyCamera::create(std::move(cam).value(), std::make_shared<core::SteadyClock>());
    if (!faulty)
        return faulty.error();
    (*faulty)->timeoutNext(s.timeoutFirstCaptures);
    if (s.disconnectAfterFrames >= 0)
        (*faulty)->disconnectAfter(s.disconnectAfterFrames);
    return std::unique_ptr<hw::Camera>(std::move(faulty).value());
}

/// Modbus TCP or RTU (config.modbus.transport), any register map.
StageResult openModbusStage(const StageConfig& config) {
    auto s = drivers::ModbusStage::create(config.modbus);
    if (!s)
        return s.error();
    return std::unique_ptr<hw::Stage>(std::move(s).value());
}

StageResult openSimStage(const StageConfig& config) {
    auto s = sim::SimStage::create(config.sim);
    if (!s)
        return s.error();
    return std::unique_ptr<hw::Stage>(std::move(s).value());
}

struct StageDriver {
    const char* name;
    StageResult (*open)(const StageConfig&);
    bool simulated;
};
/// The stage registry: a new stage driver adds its entry here (and its keys in
/// config/stage_config.cpp).
constexpr std::array<StageDriver, 2> kStageDrivers = {{
    {"modbus", openModbusStage, false},
    {"sim", openSimStage, true},
}};

std::string joined(const std::vector<std::string>& names) {
    std::string out;
    for (const auto& n : names)
        out += (out.empty() ? "" : ", ") + n;
    return out;
}

struct CameraDriver {
    const char* name;
    CameraResult (*open)(const CameraConfig&, StagePosition);
    bool simulated;
};
/// The camera registry: a new camera driver adds its entry here.
constexpr std::array<CameraDriver, 3> kCameraDrivers = {{
    {"v4l2", openV4l2, false},
    {"libcamera", openLibcamera, false},
    {"sim", openSimCamera, true},
}};

} // namespace

core::Result<std::unique_ptr<hw::Stage>> openStage(const StageConfig& config, bool& simulated) {
    simulated = config.driver == "sim";
    for (const StageDriver& d : kStageDrivers)
        if (config.driver == d.name) {
            simulated = d.simulated;
            return d.open(config);
        }
    return makeError(ErrorCode::InvalidArgument, "stage.driver: no driver \"" + config.driver +
                                                     "\" (known: " + joined(stageDriverNames()) +
                                                     ")");
}

core::Result<std::unique_ptr<hw::Camera>>
openCamera(const CameraConfig& config, std::function<hw::StagePosition()> stagePosition,
           bool& simulated) {
    simulated = config.driver == "sim";
    if (config.driver.empty())
        return makeError(ErrorCode::InvalidArgument,
                         "camera: the station file has no [camera] section");
    for (const CameraDriver& d : kCameraDrivers)
        if (config.driver == d.name) {
            simulated = d.simulated;
            return d.open(config, std::move(stagePosition));
        }
    return makeError(ErrorCode::InvalidArgument, "camera.driver: no driver \"" + config.driver +
                                                     "\" (known: " + joined(cameraDriverNames()) +
                                                     ")");
}

std::vector<std::string> stageDriverNames() {
    std::vector<std::string> out;
    for (const StageDriver& d : kStageDrivers)
        out.emplace_back(d.name);
    return out;
}

std::vector<std::string> cameraDriverNames() {
    std::vector<std::string> out;
    for (const CameraDriver& d : kCameraDrivers)
        out.emplace_back(d.name);
    return out;
}

} // namespace slicestation::daemon
