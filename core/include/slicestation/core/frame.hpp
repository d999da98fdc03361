#pragma once
/// One captured image that owns its pixels and the metadata of its capture.
/// Pixels are tightly packed rows (stride = width * bytesPerPixel), native-endian for 16-bit.

#include "slicestation/core/stage.hpp"

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <vector>

namespace slicestation::hw {

enum class PixelFormat {
    Mono8,  ///< 1 byte per pixel
    Mono16, ///< 2 bytes per pixel, native endian
    Rgb8,   ///< 3 bytes per pixel, R then G then B
};

int bytesPerPixel(PixelFormat f) noexcept;
const char* toString(PixelFormat f) noexcept;

struct FrameMetadata {
    std::int64_t exposureUs = 0; ///< exposure actually used
    double analogueGain = 1.0;   ///< gain actually used
    double redGain = 1.0;        ///< white-balance gains actually used (1 for mono)
    double blueGain = 1.0;
    std::int64_t timestampNs = 0;       ///< sensor or driver timestamp, CLOCK_MONOTONIC
    std::uint64_t sequence = 0;         ///< frame counter of the device since it started
    std::optional<StagePosition> stage; ///< set when the model knows where the stage was
};

class Frame {
public:
    Frame() = default;
    /// Zero-filled frame of the given geometry (width, height >= 0).
    Frame(PixelFormat format, int width, int height);

    PixelFormat format() const noexcept { return format_; }
    int width() const noexcept { return width_; }
    int height() const noexcept { return height_; }
    std::size_t stride() const noexcept {
        return static_cast<std::size_t>(width_) * bytesPerPixel(format_);
    }
    bool empty() const noexcept { return pixels_.empty(); }
    std::uint8_t* row(int y) noexcept {
        return pixels_.data() + stride() * static_cast<std::size_t>(y);
    }
    const std::uint8_t* row(int y) const noexcept {
        return pixels_.data() + stride() * static_cast<std::size_t>(y);
    }
    std::vector<std::uint8_t>& bytes() noexcept { return pixels_; }
    const std::vector<std::uint8_t>& bytes() const noexcept { return pixels_; }

    FrameMetadata metadata;

private:
    PixelFormat format_ = PixelFormat::Mono8;
    int width_ = 0;
    int height_ = 0;
    std::vector<std::uint8_t> pixels_;
};

} // namespace slicestation::hw
