// Section and label images (TIFF, PNG, ...) and OME-TIFF read back: what `slicectl register`,
// the atlas reader and the daemon read from disk.
#include "fuzz_common.hpp"
#include "slicestation/core/image_file.hpp"
#include "slicestation/daemon/storage/ome_tiff.hpp"

using namespace slicestation;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const auto file = fuzz::inputFile(data, size, "image");
    (void)core::readImage(file);
    (void)daemon::readOmeTiff(file);
    return 0;
}
