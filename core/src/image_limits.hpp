// Internal to core: the size limits of a decoded image (kMaxImagePixels, kMaxImageBytes), one
// check shared by the TIFF, PNG and JPEG readers (image_file.cpp) and the decoders (codec.cpp).
#pragma once

#include "slicestation/core/image_file.hpp"
#include "slicestation/core/result.hpp"

#include <cstdint>
#include <string>

namespace slicestation::core {

inline std::string megabytes(std::uint64_t bytes) {
    return std::to_string((bytes + (1u << 20) - 1) >> 20) + " MiB";
}

/// Refuses an image whose decoded size exceeds kMaxImagePixels or kMaxImageBytes.
inline Result<void> checkImageSize(const std::string& where, std::uint64_t width,
                                   std::uint64_t height, int channels, int sampleBytes) {
    const std::uint64_t pixels = width * height; // both < 2^32: no overflow
    const std::uint64_t bytes =
        pixels * static_cast<std::uint64_t>(channels) * static_cast<std::uint64_t>(sampleBytes);
    if (pixels > kMaxImagePixels || bytes > kMaxImageBytes) {
        return makeError(ErrorCode::Unsupported, where + ": image of " + std::to_string(width) +
                                                     " x " + std::to_string(height) + " px, " +
                                                     std::to_string(channels) + " channel(s) of " +
                                                     std::to_string(8 * sampleBytes) + " bits (" +
                                                     megabytes(bytes) + ") exceeds the limit of " +
                                                     std::to_string(kMaxImagePixels) + " px and " +
                                                     megabytes(kMaxImageBytes));
    }
    return {};
}

} // namespace slicestation::core
