#pragma once
/// The station file (TOML): which stage and camera drivers to use and how they are wired.
/// Simulation is chosen explicitly (driver = "sim") and announced by whoever opens it; nothing
/// falls back to a simulator. Errors are InvalidArgument naming the key (e.g. stage.axes.x.slave),
/// NotFound for a missing file. Read like every document (config_document.hpp: size, depth and
/// number limits) and strict: a key no table reads is refused, with the nearest known key, and so
/// is a key of another driver or transport (`stage.host: only for transport = "tcp"`).

#include "slicestation/core/camera.hpp"
#include "slicestation/core/result.hpp"
#include "slicestation/core/stage.hpp"
#include "slicestation/drivers/modbus_stage.hpp"
#include "slicestation/sim/sim_camera.hpp"
#include "slicestation/sim/sim_stage.hpp"
#include "slicestation/sim/virtual_slide.hpp"

#include <chrono>
#include <cstddef>
#include <filesystem>
#include <functional>
#include <memory>
#include <string>
#include <vector>

namespace slicestation::daemon {

inline constexpr std::size_t kMaxSimSections = 1'000;     ///< camera.sim.sections / images
inline constexpr double kMaxSimSlideSidePx = 40'000;      ///< the virtual slide image, a side
inline constexpr double kMaxSimSlidePixels = 400'000'000; ///< ... and in all

struct StageConfig {
    std::string driver;                ///< "modbus" or "sim"
    drivers::ModbusStageConfig modbus; ///< driver = "modbus"
    sim::SimStageConfig sim;           ///< driver = "sim"
    std::chrono::milliseconds moveTimeout{10'000};
    std::chrono::milliseconds homeTimeout{60'000};
};

/// [camera.sim]: the simulated camera, the virtual slide it looks at and injected faults.
struct SimCameraSection {
    sim::VirtualSlideSpec slide;               ///< generated sections (when `images` is empty)
    std::vector<std::filesystem::path> images; ///< real section images (relative to the file)
    double imagesUmPerPx = 20;                 ///< pixel size of `images`
    double sensorUmPerPx = 2.0;
    double focusZUm = 2'500, focusTiltX = 0.0, focusTiltY = 0.0;
    double blurSigmaPxPerUm = 0.15;
    int timeoutFirstCaptures = 0;   ///< FaultyCamera: the first N captures time out
    int disconnectAfterFrames = -1; ///< FaultyCamera: disconnect after N frames (-1: never)
};

/// [camera]; optional in a station file (driver empty when absent).
struct CameraConfig {
    std::string driver; ///< "v4l2", "libcamera" or "sim"; empty: no [camera] section
    std::string device = "/dev/video0"; ///< v4l2
    std::string cameraId;               ///< libcamera (empty: the first camera)
    hw::CameraSettings settings;        ///< format, width, height, exposure_us, gain, red/blue_gain
    std::chrono::milliseconds captureTimeout{5'000};
    int settleFrames = 3; ///< v4l2, libcamera: frames dropped after (re)configuring
    SimCameraSection sim; ///< driver = "sim"
};

struct StationConfig {
    StageConfig stage;
    CameraConfig camera;
    std::filesystem::path file;
};

core::Result<StationConfig> loadStationConfig(const std::filesystem::path& file);
core::Result<StationConfig> parseStationConfig(std::string_view toml,
                                               const std::filesystem::path& origin);

} // namespace slicestation::daemon
