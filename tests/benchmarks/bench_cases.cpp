#include "bench_cases.hpp"

#include "slicestation/core/nrrd.hpp"
#include "slicestation/core/ontology.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/sim/builtin_atlas.hpp"

#include <algorithm>
#include <cmath>
#include <sstream>

namespace slicestation::bench {

std::string BenchCase::describe() const {
    std::ostringstream s;
    s << "case " << index << " seed " << seed << " plane " << plane
      << (options.stain == sim::Stain::Brightfield ? " brightfield" : " fluorescence");
    if (options.damage.tear) s << " tear";
    if (options.damage.missing) s << " missing";
    if (options.damage.fragment) s << " fragment";
    return s.str();
}

core::Result<AtlasSource> loadAtlasPlanes(const std::filesystem::path& sharedDir, int count) {
    AtlasSource src;
    const auto dir = sharedDir / "atlas" / "allen-ccf-2017";
    if (!std::filesystem::exists(dir / "annotation_25_quicknii.nrrd")) {
        src.name = "builtin";
        for (int i = 0; i < count; ++i) {
            src.planes.push_back(sim::builtinAtlasPlane(0.15 + 0.7 * i / std::max(1, count - 1)));
            src.apIndices.push_back(-1);
        }
        return src;
    }
    auto vol = core::readNrrd(dir / "annotation_25_quicknii.nrrd");
    if (!vol) return vol.error();
    auto onto = core::readOntologyCsv(dir / "structure_tree_safe_2017.csv");
    if (!onto) return onto.error();
    src.name = "allen-ccf-25um";
    // AP 25-um indices from the front of the olfactory bulbs to the hind brainstem, avoiding the
    // few extreme planes where the brain is a sliver.
    const int first = 60, last = 470;
    for (int i = 0; i < count; ++i) {
        const int ap = first + (last - first) * i / std::max(1, count - 1);
        auto plane = pipeline::coronalPlane(*vol, pipeline::VolumeAxes::QuickNii, ap);
        if (!plane) return plane.error();
        src.planes.push_back(
            pipeline::collapseLabels(*plane, *onto, pipeline::majorRegionIds(), 8));
        src.apIndices.push_back(ap);
    }
    return src;
}

std::vector<BenchCase> makeCases(int count, int planes, cv::Size size) {
    std::vector<BenchCase> cases;
    for (int i = 0; i < count; ++i) {
        BenchCase c;
        c.index = i;
        c.seed = 1000 + static_cast<std::uint64_t>(i);
        // Pair clean and damaged cases on the same plane so the comparison is like for like.
        c.plane = (i / 2 * 7) % std::max(1, planes);
        c.options.seed = c.seed;
        c.options.imageSize = size;
        // Brightfield on one clean and one damaged case in every eight.
        c.options.stain = (i % 8 == 2 || i % 8 == 3) ? sim::Stain::Brightfield : sim::Stain::Fluorescence;
        if (i % 2 == 1) {
            switch ((i / 2) % 4) {
            case 0: c.options.damage.tear = true; break;
            case 1: c.options.damage.missing = true; break;
            case 2: c.options.damage.fragment = true; break;
            default: c.options.damage.tear = c.options.damage.missing = true; break;
            }
        }
        cases.push_back(c);
    }
    return cases;
}

Errors landmarkErrors(const std::vector<sim::Landmark>& truth,
                      const std::vector<cv::Point2d>& mapped) {
    Errors e;
    std::vector<double> d;
    for (size_t i = 0; i < truth.size() && i < mapped.size(); ++i)
        d.push_back(cv::norm(mapped[i] - truth[i].atlas));
    if (d.empty()) return e;
    double ss = 0;
    for (double x : d) ss += x * x;
    e.rmse = std::sqrt(ss / double(d.size()));
    std::sort(d.begin(), d.end());
    e.median = d[d.size() / 2];
    e.max = d.back();
    return e;
}

} // namespace slicestation::bench
