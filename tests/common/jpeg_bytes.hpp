#pragma once
// Hand-edited JPEG streams for tests: where a baseline JPEG's frame header (SOF0, ITU T.81
// B.2.2) lies, so that a test can change the size it claims or its coding process.
#include <cstddef>
#include <cstdint>

namespace slicestation::testing_jpeg {

/// The SOF0 marker (FF C0) in `data`: marker, length (2), precision, height (2), width (2)
/// follow from it; nullptr when there is none with its header inside `size`.
inline std::uint8_t* findSof0(std::uint8_t* data, std::size_t size) {
    for (std::size_t i = 2; i + 9 < size; ++i)
        if (data[i] == 0xFF && data[i + 1] == 0xC0)
            return data + i;
    return nullptr;
}

/// Makes the frame header at `sof` (from findSof0) claim `width` x `height` px.
inline void claimSize(std::uint8_t* sof, int width, int height) {
    sof[5] = static_cast<std::uint8_t>(height >> 8), sof[6] = static_cast<std::uint8_t>(height);
    sof[7] = static_cast<std::uint8_t>(width >> 8), sof[8] = static_cast<std::uint8_t>(width);
}

} // namespace slicestation::testing_jpeg
