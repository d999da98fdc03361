// An atlas stack's manifest.json, as the daemon and slicectl read it at start.
#include "fuzz_common.hpp"
#include "slicestation/daemon/storage/atlas_stack.hpp"

using namespace slicestation;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const auto file = fuzz::inputFile(data, size, "manifest.json");
    auto stack = daemon::readStack(file);
    (void)stack; // slices name files anywhere (/dev/zero too): reading them is not the manifest's
                 // test
    return 0;
}
