// The station file (TOML): devices, [daemon], [scan], [alerts]. Read as slicestationd and
// slicectl read it; anything but a clean Result is a finding.
#include "slicestation/daemon/config/config_document.hpp"
#include "slicestation/daemon/config/daemon_settings.hpp"
#include "slicestation/daemon/config/station_config.hpp"

#include <cstddef>
#include <cstdint>
#include <string_view>

using namespace slicestation;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const std::string_view text(reinterpret_cast<const char*>(data), size);
    (void)daemon::parseStationConfig(text, "station.toml");
    auto doc = daemon::parseDocument(text, daemon::DocumentFormat::Toml, "station.toml");
    if (doc)
        (void)daemon::parseDaemonSettings(*doc, "station.toml");
    return 0;
}
