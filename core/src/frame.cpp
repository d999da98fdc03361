#include "slicestation/core/frame.hpp"

namespace slicestation::hw {

int bytesPerPixel(PixelFormat f) noexcept {
    switch (f) {
    case PixelFormat::Mono8:
        return 1;
    case PixelFormat::Mono16:
        return 2;
    case PixelFormat::Rgb8:
        return 3;
    }
    return 1;
}

const char* toString(PixelFormat f) noexcept {
    switch (f) {
    case PixelFormat::Mono8:
        return "mono8";
    case PixelFormat::Mono16:
        return "mono16";
    case PixelFormat::Rgb8:
        return "rgb8";
    }
    return "unknown";
}

Frame::Frame(PixelFormat format, int width, int height)
    : format_(format), width_(width < 0 ? 0 : width), height_(height < 0 ? 0 : height),
      pixels_(stride() * static_cast<std::size_t>(height_), 0) {}

} // namespace slicestation::hw
