#pragma once
/// The station file (TOML): which stage and camera drivers to use and how they are wired.
/// Simulation is chosen explicitly (driver = "sim") and announced by whoever opens it; nothing
/// falls back to a simulator. Errors are InvalidArgument naming the key (e.g. stage.axes.x.slave),
/// NotFound for a missing file.

#include "slicestation/core/result.hpp"
#include "slicestation/core/stage.hpp"
#include "slicestation/drivers/modbus_stage.hpp"
#include "slicestation/sim/sim_stage.hpp"

#include <chrono>
#include <filesystem>
#include <memory>
#include <string>

namespace slicestation::daemon {

struct StageConfig {
    std::string driver;                       ///< "modbus" or "sim"
    drivers::ModbusStageConfig modbus;        ///< driver = "modbus"
    sim::SimStageConfig sim;                  ///< driver = "sim"
    std::chrono::milliseconds moveTimeout{10'000};
    std::chrono::milliseconds homeTimeout{60'000};
};

struct StationConfig {
    StageConfig stage;
    std::filesystem::path file;
};

core::Result<StationConfig> loadStationConfig(const std::filesystem::path& file);
core::Result<StationConfig> parseStationConfig(std::string_view toml, const std::filesystem::path& origin);

/// Opens the configured stage. `simulated` is set when it is a simulator (callers announce it).
core::Result<std::unique_ptr<hw::Stage>> openStage(const StageConfig& config, bool& simulated);

} // namespace slicestation::daemon
