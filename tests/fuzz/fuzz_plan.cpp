// Scan plans as a technician submits them (TOML or JSON): parse, validate, resolve against a
// station's stage limits and atlas stack. Anything but a clean Result is a finding.
#include "slicestation/daemon/config/config_document.hpp"
#include "slicestation/daemon/config/scan_plan.hpp"

#include <cstddef>
#include <cstdint>
#include <string_view>

using namespace slicestation;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const std::string_view text(reinterpret_cast<const char*>(data), size);
    const auto first = text.find_first_not_of(" \t\r\n");
    const auto format = first != std::string_view::npos && text[first] == '{'
                            ? daemon::DocumentFormat::Json
                            : daemon::DocumentFormat::Toml;
    auto doc = daemon::parseDocument(text, format, "plan");
    if (!doc)
        return 0;
    auto plan = daemon::parseScanPlan(*doc, "plan");
    if (!plan)
        return 0;
    hw::StageLimits limits;
    limits.x = {0, 75'000};
    limits.y = {0, 50'000};
    limits.z = hw::AxisRange{0, 5'000};
    std::vector<double> positions;
    for (int i = 0; i < 80; ++i)
        positions.push_back(100.0 * i);
    (void)daemon::resolveScanPlan(*plan, limits, positions, "plan");
    return 0;
}
