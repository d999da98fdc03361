#pragma once
/// Configuration to devices: the stage and the camera a station file names, opened through a
/// registry of drivers (devices.cpp: one entry per driver; a new driver adds its entry there and
/// its keys in config/station_config). Simulation is chosen explicitly (driver = "sim") and
/// announced by the caller; nothing falls back to a simulator.
#include "slicestation/core/camera.hpp"
#include "slicestation/core/result.hpp"
#include "slicestation/core/stage.hpp"
#include "slicestation/daemon/config/station_config.hpp"

#include <functional>
#include <memory>
#include <string>
#include <vector>

namespace slicestation::daemon {

/// Opens the configured stage. `simulated` is set when it is a simulator (callers announce it).
core::Result<std::unique_ptr<hw::Stage>> openStage(const StageConfig& config, bool& simulated);

/// Opens the configured camera (not yet configured: call configure(config.settings, ...)).
/// `stagePosition` tells a simulated camera where the stage is (the daemon passes the position it
/// last moved the real or simulated stage to); required for driver = "sim", unused otherwise.
/// `simulated` is set when it is a simulator (callers announce it). Building a generated virtual
/// slide takes about 0.3 s per section.
/// \return InvalidArgument (no [camera] section: names `camera`; sim without stagePosition),
///         or the driver's error (NotFound: no such device / no camera found, ...).
core::Result<std::unique_ptr<hw::Camera>>
openCamera(const CameraConfig& config, std::function<hw::StagePosition()> stagePosition,
           bool& simulated);

/// The driver names of the registry, for messages and tests.
std::vector<std::string> stageDriverNames();
std::vector<std::string> cameraDriverNames();

} // namespace slicestation::daemon
