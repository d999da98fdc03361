// NRRD volumes (the Allen annotation and template), as `slicectl atlas slice` reads them.
#include "fuzz_common.hpp"
#include "slicestation/core/nrrd.hpp"

using namespace slicestation;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const auto file = fuzz::inputFile(data, size, "volume.nrrd");
    (void)core::readNrrd(file);
    return 0;
}
