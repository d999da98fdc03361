#pragma once
// Private to storage/: text helpers the OME-TIFF file and its OME-XML share.
#include <array>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <string>

namespace slicestation::daemon::ome_text {

inline std::string quoted(const std::filesystem::path& path) {
    return "'" + path.string() + "'";
}

inline std::string formatDouble(double v) {
    std::array<char, 64> buf{};
    // Shortest text that reads back to the same double.
    const auto [end, ec] = std::to_chars(buf.data(), buf.data() + buf.size(), v);
    return ec == std::errc() ? std::string(buf.data(), end) : std::string("0");
}

} // namespace slicestation::daemon::ome_text
