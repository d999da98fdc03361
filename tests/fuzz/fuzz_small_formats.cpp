// Small text formats from outside: the points CSV of `slicectl register --points` (first byte
// even; read by core::parseCsv, the one CSV reader, which the ontology shares) and the OME-XML
// block of an OME-TIFF (first byte odd; parsed by pugixml).
#include "slicestation/daemon/cli/points_csv.hpp"
#include "slicestation/daemon/storage/ome_tiff.hpp"

#include <cstddef>
#include <cstdint>
#include <string_view>

using namespace slicestation;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    if (size == 0)
        return 0;
    const std::string_view text(reinterpret_cast<const char*>(data + 1), size - 1);
    if (data[0] % 2 == 0)
        (void)daemon::parsePointsCsv(text);
    else
        (void)daemon::parseOmeXml(text);
    return 0;
}
