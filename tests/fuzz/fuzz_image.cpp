// Section and label images (TIFF, PNG, ...) and OME-TIFF read back: what `slicectl register`,
// the atlas reader and the daemon read from disk; and the same bytes as a camera's MJPEG frame.
#include "fuzz_common.hpp"
#include "slicestation/core/codec.hpp"
#include "slicestation/core/image_file.hpp"
#include "slicestation/daemon/storage/ome_tiff.hpp"

using namespace slicestation;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const auto file = fuzz::inputFile(data, size, "image");
    (void)core::readImage(file);
    (void)daemon::readOmeTiff(file);
    // A camera's MJPEG frame: decoded in memory once its header claims the size the camera
    // negotiated (the drivers' check; no camera here negotiates more than 16 Mpx).
    if (const auto claimed = core::jpegFrameSize(data, size);
        claimed && std::int64_t{claimed->width} * claimed->height <= 4096 * 4096) {
        (void)core::decodeJpeg(std::span(data, size), core::JpegPixels::Rgb, "MJPEG frame");
    }
    return 0;
}
