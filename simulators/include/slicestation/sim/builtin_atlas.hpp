#pragma once
/// A procedural, built-in coronal atlas of a mouse-like brain.
///
/// It lets tests, benchmarks and the demo run without the Allen volumes. The regions carry the
/// real Allen CCFv3 structure ids of the structures they imitate, so code that handles a real
/// Allen plane (collapsed to major regions) handles these planes unchanged.
/// Threading: both functions are pure and re-entrant.

#include <opencv2/core/mat.hpp>

#include <cstdint>
#include <string>
#include <vector>

namespace slicestation::sim {

struct RegionInfo {
    std::int32_t id;        ///< Allen CCFv3 structure id
    std::string name;       ///< Allen name, e.g. "Caudoputamen"
    std::string acronym;    ///< Allen acronym, e.g. "CP"
    std::uint32_t colorRgb; ///< Allen colour, 0xRRGGBB
};

/// Allen ids used by the built-in atlas for the structures the section generator treats apart.
inline constexpr std::int32_t kFiberTractsId = 1009;
inline constexpr std::int32_t kVentricularSystemsId = 73;

/// The regions of the built-in atlas (ids > 0; 0 = outside the brain), in a fixed order.
const std::vector<RegionInfo>& builtinRegions();

/// A coronal label plane of a procedural, bilaterally symmetric mouse-like brain, CV_32S, 0
/// outside, every other value an id of builtinRegions().
///
/// apFraction runs from the front (0, olfactory/striatal level) to the back (1, midbrain level)
/// and is clamped to [0, 1]; the outline and the internal regions change smoothly with it, so a
/// stack of planes looks like a series. The plane is exactly mirror-symmetric about its vertical
/// centre line (column x maps to size.width - 1 - x). At mid levels the shape fills about 85% of
/// the width and is about 1.4 times wider than tall; boundaries are smooth analytic curves
/// evaluated at pixel centres. Returns an empty Mat when size has a side < 1.
cv::Mat builtinAtlasPlane(double apFraction = 0.5, cv::Size size = {456, 320});

} // namespace slicestation::sim
