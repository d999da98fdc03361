#pragma once
// Shared by the libFuzzer targets: a private scratch folder for inputs that the code under test
// only reads from a path (images, volumes, manifests). tmpfs when the machine has it.
#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <string>

namespace slicestation::fuzz {

inline const std::filesystem::path& scratchDir() {
    static const std::filesystem::path dir = [] {
        const std::filesystem::path shm = "/dev/shm";
        std::error_code ec;
        const auto base =
            std::filesystem::is_directory(shm, ec) ? shm : std::filesystem::temp_directory_path();
        auto d = base / ("slst-fuzz-" + std::to_string(::getpid()));
        std::filesystem::create_directories(d);
        return d;
    }();
    return dir;
}

/// Writes the input to `name` in the scratch folder and returns its path.
inline std::filesystem::path inputFile(const std::uint8_t* data, std::size_t size,
                                       const std::string& name) {
    const auto path = scratchDir() / name;
    std::ofstream out(path, std::ios::binary | std::ios::trunc);
    out.write(reinterpret_cast<const char*>(data), static_cast<std::streamsize>(size));
    return path;
}

} // namespace slicestation::fuzz
