#pragma once
/// The benchmark's fixed set of generated sections: real atlas planes (Allen CCFv3, 25 um,
/// collapsed to the paper's major regions) when ../shared is present, the built-in atlas
/// otherwise, warped by known transforms, some damaged, some brightfield.

#include "slicestation/core/ontology.hpp"
#include "slicestation/core/result.hpp"
#include "slicestation/sim/section_generator.hpp"
#include "slicestation/sim/section_generator_b.hpp"

#include <opencv2/core.hpp>

#include <filesystem>
#include <string>
#include <vector>

namespace slicestation::bench {

struct AtlasSource {
    std::string name;            ///< "allen-ccf-25um" or "builtin"
    std::vector<cv::Mat> planes; ///< label planes, CV_32S, one per case slot
    std::vector<int> apIndices;  ///< AP index of each plane (25 um grid), -1 for built-in
    double umPerPx = 25.0;
    /// The same planes with every Allen id (not collapsed); equal to `planes` for built-in.
    std::vector<cv::Mat> fullPlanes;
    /// The Allen average template (100 um) on each plane's 25 um grid, CV_32F, interpolated
    /// between the two nearest 100 um planes; empty for built-in.
    std::vector<cv::Mat> templatePlanes;
    /// The 100 um template plane nearest each plane (CV_32F, 100 um pixels, mirrored like
    /// templatePlanes): elastix's moving image. Empty for built-in.
    std::vector<cv::Mat> templatePlanes100;
    bool templateMirrored = false; ///< the template's left-right axis runs the other way
    core::Ontology ontology;       ///< empty for built-in
};

/// atlas.templatePlanes100[plane]; an empty Mat when there is none.
cv::Mat templatePlane100(const AtlasSource& atlas, int plane);

/// templatePlane100(atlas, plane) resampled (bilinear) onto the 25 um label grid of `size`, as the
/// registration's atlas intensity; empty when there is none.
cv::Mat templateOnLabelGrid(const AtlasSource& atlas, int plane, cv::Size size);

/// Generator families of the benchmark: the first (sim::generateSection), the second
/// (sim::generateSectionB, stains other than the template), the second family rendered from
/// the Allen average template, and the first family with the damage models and not-damage
/// anatomy of issue 18 (its own seeds; named "1m").
enum class Family { First, Second, Template, FirstModels };
/// The first family's generator renders it (First and FirstModels).
inline bool firstGenerator(Family family) {
    return family == Family::First || family == Family::FirstModels;
}
const char* familyName(Family family);

struct BenchCase {
    Family family = Family::First;
    int index = 0;
    std::uint64_t seed = 0;
    int plane = 0;                   ///< into AtlasSource::planes
    sim::GeneratorOptions options;   ///< first family
    sim::GeneratorOptionsB optionsB; ///< second family and template (templatePlane set later)
    bool brightfield() const {
        return firstGenerator(family) ? options.stain == sim::Stain::Brightfield
                                      : optionsB.brightfield;
    }
    bool damaged() const {
        if (!firstGenerator(family))
            return optionsB.damage.any();
        return options.damage.any();
    }
    std::string describe() const;
};

/// Loads the real atlas planes (quicknii 25 um volume + ontology) spread over the AP range, or
/// builds built-in planes when `sharedDir` lacks them.
core::Result<AtlasSource> loadAtlasPlanes(const std::filesystem::path& sharedDir, int count);

/// `count` cases: alternating clean and damaged (tear, missing, fragment, tear+missing), a
/// quarter brightfield (clean and damaged alike), image size `size`.
std::vector<BenchCase> makeCases(int count, int planes, cv::Size size);

/// The second family's `count` cases: seeds 5000 + i; alternating clean and damaged (crack,
/// bite, fragment, fold, crack+bite); stains immuno, Nissl, autofluorescence, immuno in turn
/// (per pair); a quarter brightfield.
std::vector<BenchCase> makeCasesB(int count, int planes, cv::Size size);

/// The template family's `count` cases: seeds 9000 + i, all rendered from the average template
/// (fluorescence), alternating clean and damaged (crack, bite, fragment, fold).
std::vector<BenchCase> makeCasesTemplate(int count, int planes, cv::Size size);

/// The first family with issue 18's models: `count` cases, seeds 2000 + i, alternating clean and
/// damaged (crack, fold, small fragment, torn ventricle, chatter, crack + fold in turn); every
/// case, clean or damaged, in turn plain, with enlarged ventricles, with a fissure opened, or
/// both (per pair); a quarter brightfield. A damaged case whose model found no place to paint
/// (no ventricle to tear) has no damage in its truth.
std::vector<BenchCase> makeCasesModels(int count, int planes, cv::Size size);

/// A generated section of any family.
struct Section {
    cv::Mat image;
    sim::GroundTruth truth;
};
/// Generates `c` on `atlas`: the first family renders the collapsed plane, the others the plane
/// with every Allen id (and the template plane).
core::Result<Section> generate(const BenchCase& c, const AtlasSource& atlas);

/// Landmark errors (atlas px) of mapped points against the truth.
struct Errors {
    double rmse = 0, median = 0, max = 0;
};
Errors landmarkErrors(const std::vector<sim::Landmark>& truth,
                      const std::vector<cv::Point2d>& mapped);

} // namespace slicestation::bench
