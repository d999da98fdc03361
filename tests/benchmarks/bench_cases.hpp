#pragma once
/// The benchmark's fixed set of generated sections: real atlas planes (Allen CCFv3, 25 um,
/// collapsed to the paper's major regions) when ../shared is present, the built-in atlas
/// otherwise, warped by known transforms, some damaged, some brightfield.

#include "slicestation/core/result.hpp"
#include "slicestation/sim/section_generator.hpp"

#include <opencv2/core.hpp>

#include <filesystem>
#include <string>
#include <vector>

namespace slicestation::bench {

struct AtlasSource {
    std::string name;              ///< "allen-ccf-25um" or "builtin"
    std::vector<cv::Mat> planes;   ///< label planes, CV_32S, one per case slot
    std::vector<int> apIndices;    ///< AP index of each plane (25 um grid), -1 for built-in
    double umPerPx = 25.0;
};

struct BenchCase {
    int index = 0;
    std::uint64_t seed = 0;
    int plane = 0;                 ///< into AtlasSource::planes
    sim::GeneratorOptions options;
    bool damaged() const {
        return options.damage.tear || options.damage.missing || options.damage.fragment;
    }
    std::string describe() const;
};

/// Loads the real atlas planes (quicknii 25 um volume + ontology) spread over the AP range, or
/// builds built-in planes when `sharedDir` lacks them.
core::Result<AtlasSource> loadAtlasPlanes(const std::filesystem::path& sharedDir, int count);

/// `count` cases: alternating clean and damaged (tear, missing, fragment, tear+missing), a
/// quarter brightfield (clean and damaged alike), image size `size`.
std::vector<BenchCase> makeCases(int count, int planes, cv::Size size);

/// Landmark errors (atlas px) of mapped points against the truth.
struct Errors {
    double rmse = 0, median = 0, max = 0;
};
Errors landmarkErrors(const std::vector<sim::Landmark>& truth,
                      const std::vector<cv::Point2d>& mapped);

} // namespace slicestation::bench
