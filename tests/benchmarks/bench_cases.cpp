#include "bench_cases.hpp"

#include "slicestation/core/nrrd.hpp"
#include "slicestation/core/ontology.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/sim/builtin_atlas.hpp"

#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <sstream>

namespace slicestation::bench {

const char* familyName(Family family) {
    switch (family) {
    case Family::First:
        return "1";
    case Family::Second:
        return "2";
    case Family::Template:
        return "template";
    case Family::FirstModels:
        return "1m";
    }
    return "?";
}

std::string BenchCase::describe() const {
    std::ostringstream s;
    if (firstGenerator(family)) {
        s << (family == Family::FirstModels ? "f1m " : "") << "case " << index << " seed " << seed
          << " plane " << plane
          << (options.stain == sim::Stain::Brightfield ? " brightfield" : " fluorescence");
        if (options.damage.tear)
            s << " tear";
        if (options.damage.missing)
            s << " missing";
        if (options.damage.fragment)
            s << " fragment";
        const sim::DamageOptions& d = options.damage;
        for (const auto& [on, name] : {std::pair{d.crack, " crack"},
                                       {d.fold, " fold"},
                                       {d.smallFragment, " small-fragment"},
                                       {d.tornVentricle, " torn-ventricle"},
                                       {d.chatter, " chatter"}})
            if (on)
                s << name;
        if (options.anatomy.ventricleGrowthFrac > 0)
            s << " (enlarged ventricles)";
        if (options.anatomy.fissureOpenFrac > 0)
            s << " (fissure opened)";
        return s.str();
    }
    s << "f" << familyName(family) << " case " << index << " seed " << seed << " plane " << plane
      << " " << sim::toString(optionsB.stain) << (optionsB.brightfield ? " brightfield" : "");
    if (optionsB.damage.crack)
        s << " crack";
    if (optionsB.damage.bite)
        s << " bite";
    if (optionsB.damage.fragment)
        s << " fragment";
    if (optionsB.damage.fold)
        s << " fold";
    return s.str();
}

namespace {

/// Which way round the Allen template's left-right axis runs relative to the QuickNII volume:
/// decided from the data by comparing the two annotation volumes (full ids), not assumed.
bool mirroredAgainst(const core::Volume& ann100, const cv::Mat& qnPlane25, int ap25) {
    const int ap100 = std::clamp(int(std::lround((ap25 - 1.5) / 4)), 0, ann100.sizes[0] - 1);
    auto p = pipeline::coronalPlane(ann100, pipeline::VolumeAxes::Allen, ap100);
    if (!p)
        return false;
    long same = 0, mirrored = 0;
    for (int r = 0; r < p->rows; ++r)
        for (int c = 0; c < p->cols; ++c) {
            const int a = p->at<int>(r, c);
            if (a == 0)
                continue;
            const int rr = std::min(qnPlane25.rows - 1, r * 4 + 1);
            same += a == qnPlane25.at<int>(rr, std::min(qnPlane25.cols - 1, c * 4 + 1));
            mirrored +=
                a == qnPlane25.at<int>(rr, std::min(qnPlane25.cols - 1, (p->cols - 1 - c) * 4 + 1));
        }
    return mirrored > same;
}

/// The 100 um template on the 25 um plane `ap25`'s grid: the centre of 100 um voxel i is 25 um
/// pixel 4 i + 1.5, along every axis.
cv::Mat templateOnGrid(const core::Volume& templ, int ap25, bool mirror, cv::Size size) {
    const double apf = std::clamp((ap25 - 1.5) / 4, 0.0, templ.sizes[0] - 1.001);
    const int a0 = int(apf);
    const int a1 = std::min(a0 + 1, templ.sizes[0] - 1);
    const double wa = apf - a0;
    const int rows = templ.sizes[1], cols = templ.sizes[2];
    cv::Mat t100(rows, cols, CV_32F);
    for (int r = 0; r < rows; ++r)
        for (int c = 0; c < cols; ++c) {
            const int cc = mirror ? cols - 1 - c : c;
            t100.at<float>(r, c) = float((1 - wa) * templ.at(a0, r, cc) + wa * templ.at(a1, r, cc));
        }
    cv::Mat mapX(size, CV_32F), mapY(size, CV_32F), out;
    for (int r = 0; r < size.height; ++r)
        for (int c = 0; c < size.width; ++c) {
            mapX.at<float>(r, c) = float((c - 1.5) / 4);
            mapY.at<float>(r, c) = float((r - 1.5) / 4);
        }
    cv::remap(t100, out, mapX, mapY, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
    return out;
}

} // namespace

core::Result<AtlasSource> loadAtlasPlanes(const std::filesystem::path& sharedDir, int count) {
    AtlasSource src;
    const auto dir = sharedDir / "atlas" / "allen-ccf-2017";
    if (!std::filesystem::exists(dir / "annotation_25_quicknii.nrrd")) {
        src.name = "builtin";
        for (int i = 0; i < count; ++i) {
            src.planes.push_back(sim::builtinAtlasPlane(0.15 + 0.7 * i / std::max(1, count - 1)));
            src.fullPlanes.push_back(src.planes.back());
            src.apIndices.push_back(-1);
        }
        return src;
    }
    auto vol = core::readNrrd(dir / "annotation_25_quicknii.nrrd");
    if (!vol)
        return vol.error();
    auto onto = core::readOntologyCsv(dir / "structure_tree_safe_2017.csv");
    if (!onto)
        return onto.error();
    src.name = "allen-ccf-25um";
    // AP 25-um indices from the front of the olfactory bulbs to the hind brainstem, avoiding the
    // few extreme planes where the brain is a sliver.
    const int first = 60, last = 470;
    for (int i = 0; i < count; ++i) {
        const int ap = first + (last - first) * i / std::max(1, count - 1);
        auto plane = pipeline::coronalPlane(*vol, pipeline::VolumeAxes::QuickNii, ap);
        if (!plane)
            return plane.error();
        src.planes.push_back(pipeline::collapseLabels(*plane, *onto, pipeline::majorRegionIds(),
                                                      pipeline::kOtherRegionId));
        src.fullPlanes.push_back(*plane);
        src.apIndices.push_back(ap);
    }
    src.ontology = std::move(*onto);
    auto templ = core::readNrrd(dir / "average_template_100.nrrd");
    auto ann100 = core::readNrrd(dir / "annotation_100.nrrd");
    if (templ && ann100) {
        // Decided once, on a mid plane, for all.
        const size_t mid = src.fullPlanes.size() / 2;
        src.templateMirrored = mirroredAgainst(*ann100, src.fullPlanes[mid], src.apIndices[mid]);
        for (size_t i = 0; i < src.fullPlanes.size(); ++i) {
            src.templatePlanes.push_back(templateOnGrid(
                *templ, src.apIndices[i], src.templateMirrored, src.fullPlanes[i].size()));
            const int ap100 =
                std::clamp(static_cast<int>(std::lround((src.apIndices[i] + 0.5) / 4 - 0.5)), 0,
                           templ->sizes[0] - 1);
            cv::Mat moving(templ->sizes[1], templ->sizes[2], CV_32F);
            for (int r = 0; r < moving.rows; ++r)
                for (int col = 0; col < moving.cols; ++col)
                    moving.at<float>(r, col) = float(
                        templ->at(ap100, r, src.templateMirrored ? moving.cols - 1 - col : col));
            src.templatePlanes100.push_back(moving);
        }
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
        c.options.stain =
            (i % 8 == 2 || i % 8 == 3) ? sim::Stain::Brightfield : sim::Stain::Fluorescence;
        if (i % 2 == 1) {
            switch ((i / 2) % 4) {
            case 0:
                c.options.damage.tear = true;
                break;
            case 1:
                c.options.damage.missing = true;
                break;
            case 2:
                c.options.damage.fragment = true;
                break;
            default:
                c.options.damage.tear = c.options.damage.missing = true;
                break;
            }
        }
        cases.push_back(c);
    }
    return cases;
}

std::vector<BenchCase> makeCasesModels(int count, int planes, cv::Size size) {
    std::vector<BenchCase> cases;
    for (int i = 0; i < count; ++i) {
        BenchCase c;
        c.family = Family::FirstModels;
        c.index = i;
        c.seed = 2000 + static_cast<std::uint64_t>(i);
        c.plane = (i / 2 * 7 + 3) % std::max(1, planes);
        c.options.seed = c.seed;
        c.options.imageSize = size;
        c.options.stain =
            (i % 8 == 2 || i % 8 == 3) ? sim::Stain::Brightfield : sim::Stain::Fluorescence;
        const int anatomy = (i / 2) % 4;
        if (anatomy == 1 || anatomy == 3)
            c.options.anatomy.ventricleGrowthFrac = 0.01 + 0.002 * (i % 5);
        if (anatomy == 2 || anatomy == 3)
            c.options.anatomy.fissureOpenFrac = 0.006 + 0.002 * (i % 5);
        if (i % 2 == 1) {
            auto& d = c.options.damage;
            switch ((i / 2) % 6) {
            case 0:
                d.crack = true;
                break;
            case 1:
                d.fold = true;
                break;
            case 2:
                d.smallFragment = true;
                break;
            case 3:
                d.tornVentricle = true;
                break;
            case 4:
                d.chatter = true;
                break;
            default:
                d.crack = d.fold = true;
                break;
            }
        }
        cases.push_back(c);
    }
    return cases;
}

cv::Mat templatePlane100(const AtlasSource& atlas, int plane) {
    if (plane < 0 || size_t(plane) >= atlas.templatePlanes100.size())
        return {};
    return atlas.templatePlanes100[size_t(plane)];
}

cv::Mat templateOnLabelGrid(const AtlasSource& atlas, int plane, cv::Size size) {
    const cv::Mat t100 = templatePlane100(atlas, plane);
    if (t100.empty())
        return {};
    // The centre of 100 um voxel i is 25 um pixel 4 i + 1.5.
    cv::Mat t25;
    cv::warpAffine(t100, t25, cv::Matx23d(0.25, 0, -1.5 / 4, 0, 0.25, -1.5 / 4), size,
                   cv::INTER_LINEAR | cv::WARP_INVERSE_MAP, cv::BORDER_CONSTANT, 0);
    return t25;
}

std::vector<BenchCase> makeCasesB(int count, int planes, cv::Size size) {
    std::vector<BenchCase> cases;
    const sim::StainB stains[] = {sim::StainB::Immuno, sim::StainB::Nissl,
                                  sim::StainB::Autofluorescence, sim::StainB::Immuno};
    for (int i = 0; i < count; ++i) {
        BenchCase c;
        c.family = Family::Second;
        c.index = i;
        c.seed = 5000 + static_cast<std::uint64_t>(i);
        c.plane = (i / 2 * 5 + 3) % std::max(1, planes);
        c.optionsB.seed = c.seed;
        c.optionsB.imageSize = size;
        c.optionsB.stain = stains[(i / 2) % 4];
        c.optionsB.brightfield = i % 8 == 4 || i % 8 == 5;
        if (i % 2 == 1) {
            auto& d = c.optionsB.damage;
            switch ((i / 2) % 5) {
            case 0:
                d.crack = true;
                break;
            case 1:
                d.bite = true;
                break;
            case 2:
                d.fragment = true;
                break;
            case 3:
                d.fold = true;
                break;
            default:
                d.crack = d.bite = true;
                break;
            }
        }
        cases.push_back(c);
    }
    return cases;
}

std::vector<BenchCase> makeCasesTemplate(int count, int planes, cv::Size size) {
    std::vector<BenchCase> cases;
    for (int i = 0; i < count; ++i) {
        BenchCase c;
        c.family = Family::Template;
        c.index = i;
        c.seed = 9000 + static_cast<std::uint64_t>(i);
        c.plane = (i / 2 * 3 + 1) % std::max(1, planes);
        c.optionsB.seed = c.seed;
        c.optionsB.imageSize = size;
        c.optionsB.stain = sim::StainB::Template;
        if (i % 2 == 1) {
            auto& d = c.optionsB.damage;
            switch ((i / 2) % 4) {
            case 0:
                d.crack = true;
                break;
            case 1:
                d.bite = true;
                break;
            case 2:
                d.fragment = true;
                break;
            default:
                d.fold = true;
                break;
            }
        }
        cases.push_back(c);
    }
    return cases;
}

core::Result<Section> generate(const BenchCase& c, const AtlasSource& atlas) {
    if (firstGenerator(c.family)) {
        auto g = sim::generateSection(atlas.planes[size_t(c.plane)], c.options);
        if (!g)
            return g.error();
        return Section{g->image, std::move(g->truth)};
    }
    sim::GeneratorOptionsB o = c.optionsB;
    o.atlasUmPerPx = atlas.umPerPx;
    if (c.family == Family::Template) {
        if (atlas.templatePlanes.empty())
            return core::makeError(core::ErrorCode::NotFound,
                                   "the template family needs average_template_100.nrrd");
        o.templatePlane = atlas.templatePlanes[size_t(c.plane)];
    }
    auto g = sim::generateSectionB(atlas.fullPlanes[size_t(c.plane)], atlas.ontology, o);
    if (!g)
        return g.error();
    return Section{g->image, std::move(g->truth)};
}

Errors landmarkErrors(const std::vector<sim::Landmark>& truth,
                      const std::vector<cv::Point2d>& mapped) {
    Errors e;
    std::vector<double> d;
    for (size_t i = 0; i < truth.size() && i < mapped.size(); ++i)
        d.push_back(cv::norm(mapped[i] - truth[i].atlas));
    if (d.empty())
        return e;
    double ss = 0;
    for (double x : d)
        ss += x * x;
    e.rmse = std::sqrt(ss / double(d.size()));
    std::sort(d.begin(), d.end());
    e.median = d[d.size() / 2];
    e.max = d.back();
    return e;
}

} // namespace slicestation::bench
