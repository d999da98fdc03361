#include "slicestation/daemon/station/registration_service.hpp"

#include "slicestation/core/atomic_file.hpp"
#include "slicestation/core/image_file.hpp"
#include "slicestation/core/ontology.hpp"
#include "slicestation/daemon/storage/atlas_stack.hpp"
#include "slicestation/daemon/version.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/pipeline/overlay.hpp"

#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <set>
#include <sstream>
#include <string>
#include <utility>

namespace slicestation::daemon {
namespace {

using core::ErrorCode;
using core::makeError;
using nlohmann::json;
using Clock = std::chrono::steady_clock;

/// CPU time of the process so far (user + system, all threads, since the process started), ms.
double processCpuMs() {
    rusage u{};
    getrusage(RUSAGE_SELF, &u);
    const auto ms = [](const timeval& t) {
        return double(t.tv_sec) * 1e3 + double(t.tv_usec) * 1e-3;
    };
    return ms(u.ru_utime) + ms(u.ru_stime);
}

core::Error inFile(const core::Error& e, const std::filesystem::path& p, const char* what) {
    // Library errors may or may not name the path; make sure the user sees which input it was.
    std::string msg = e.message;
    if (msg.find(p.string()) == std::string::npos)
        msg = std::string(what) + " " + p.string() + ": " + msg;
    return makeError(e.code, msg, e.sysErrno);
}

core::Result<void> checkPixelSizes(const RegisterRequest& rq) {
    for (const auto& [option, value] : {std::pair{"--image-um-per-px", rq.imageUmPerPx},
                                        std::pair{"--atlas-um-per-px", rq.atlasUmPerPx}}) {
        // 0 is "unknown"; NaN fails every comparison, so the test is written to catch it.
        if (value != 0 && !(std::isfinite(value) && value >= kMinUmPerPx && value <= kMaxUmPerPx)) {
            std::ostringstream os;
            os << option << " " << value << " is not a finite number in [" << kMinUmPerPx << ", "
               << kMaxUmPerPx << "]";
            return makeError(ErrorCode::InvalidArgument, os.str());
        }
    }
    if ((rq.imageUmPerPx > 0) != (rq.atlasUmPerPx > 0))
        return makeError(ErrorCode::InvalidArgument,
                         "give both --image-um-per-px and --atlas-um-per-px, or neither");
    return {};
}

/// The atlas outline is what registration fits: a label image needs brain (ids) and outside (0).
core::Result<void> checkAtlasLabels(const cv::Mat& labels) {
    double lo = 0, hi = 0;
    cv::minMaxLoc(labels, &lo, &hi);
    if (hi <= 0)
        return makeError(ErrorCode::InvalidArgument,
                         "atlas label image holds no brain (every pixel is 0)");
    const int outside = labels.rows * labels.cols - cv::countNonZero(labels);
    if (lo == hi || outside == 0)
        return makeError(
            ErrorCode::InvalidArgument,
            "atlas label image has no outside (no pixel is 0)" +
                std::string(lo == hi ? ": one label, " + std::to_string(int(lo)) + ", everywhere"
                                     : "") +
                "; registration needs the brain's outline");
    return {};
}

/// What the registration gets from an atlas label image (RegisterRequest::stackRegions).
struct LabelsForRegistration {
    cv::Mat labels;       ///< the major regions when collapsed, else the labels as given
    cv::Mat regionLabels; ///< every id, for the region warp; empty when not collapsed
    std::vector<std::int32_t> ventricleIds; ///< ids of regionLabels under ventricular systems
    /// Why the labels are registered as they are when that is worse than it could be (labels
    /// below the major regions with nothing to collapse them by), for result.json's warnings.
    std::string warning = {};
};

/// Collapses labels of every Allen id to the paper's major regions, using the stack regions'
/// ontology paths; labels already of major regions, or ids without a path, are given as they
/// are. \return InvalidArgument when the regions' paths do not form an ontology.
core::Result<LabelsForRegistration> labelsForRegistration(const cv::Mat& labels,
                                                          const std::vector<StackRegion>& regions) {
    LabelsForRegistration out{labels, cv::Mat(), {}};
    if (labels.type() != CV_32S)
        return out;
    std::set<std::int32_t> major(pipeline::majorRegionIds().begin(),
                                 pipeline::majorRegionIds().end());
    major.insert(pipeline::kOtherRegionId);
    std::set<std::int32_t> seen;
    pipeline::collectIds(labels, seen);
    if (std::all_of(seen.begin(), seen.end(), [&](std::int32_t id) { return major.count(id); }))
        return out;
    if (regions.empty()) {
        out.warning = "the atlas labels are not the paper's major regions and no ontology names "
                      "them: each of the " +
                      std::to_string(seen.size()) +
                      " ids is registered as a region of its own, and ventricles and natural "
                      "fissures cannot be told from missing tissue; for Allen ids give the "
                      "ontology (slicectl register --ontology structure_tree_safe_2017.csv) or "
                      "register to a stack (slicectl atlas slice)";
        return out;
    }
    std::vector<core::Structure> structures;
    for (const StackRegion& r : regions) {
        if (r.path.empty())
            return out; // a stack written before the paths were kept: nothing to collapse by
        structures.push_back({r.id, r.path.size() > 1 ? r.path[r.path.size() - 2] : 0, r.name,
                              r.acronym, r.path, r.colorRgb});
    }
    auto ontology = core::Ontology::create(std::move(structures));
    if (!ontology)
        return makeError(ontology.error().code,
                         "the stack's regions (manifest.json) do not form an ontology: " +
                             ontology.error().message);
    for (std::int32_t id : seen)
        if (!ontology->find(std::uint32_t(id)))
            return out;
    out.labels = pipeline::collapseLabels(labels, *ontology, pipeline::majorRegionIds(),
                                          pipeline::kOtherRegionId);
    out.regionLabels = labels;
    out.ventricleIds = pipeline::idsUnder(seen, *ontology, pipeline::kVentricularSystemsId);
    return out;
}

core::Result<void> checkSectionSize(const cv::Mat& section) {
    const auto inRange = [](int side) {
        return side >= kMinSectionSidePx && side <= kMaxSectionSidePx;
    };
    if (!inRange(section.cols) || !inRange(section.rows))
        return makeError(ErrorCode::InvalidArgument,
                         "section image is " + std::to_string(section.cols) + " x " +
                             std::to_string(section.rows) + " px; sections must be " +
                             std::to_string(kMinSectionSidePx) + " to " +
                             std::to_string(kMaxSectionSidePx) + " px on each side");
    return {};
}

/// A template plane given as a file: one channel, float32 as is, 8/16-bit scaled to [0, 1], of
/// the labels' size.
core::Result<cv::Mat> readTemplateImage(const std::filesystem::path& path, cv::Size labels) {
    auto image = core::readImage(path);
    if (!image)
        return inFile(image.error(), path, "atlas template");
    if (image->channels() != 1 ||
        (image->depth() != CV_32F && image->depth() != CV_8U && image->depth() != CV_16U))
        return makeError(ErrorCode::InvalidArgument,
                         "atlas template " + path.string() +
                             ": expected a one-channel float32, 8- or 16-bit image");
    if (image->size() != labels)
        return makeError(ErrorCode::InvalidArgument,
                         "atlas template " + path.string() + ": " + std::to_string(image->cols) +
                             " x " + std::to_string(image->rows) + " px, the atlas labels are " +
                             std::to_string(labels.width) + " x " + std::to_string(labels.height));
    cv::Mat plane;
    image->convertTo(plane, CV_32F,
                     image->depth() == CV_8U    ? 1.0 / 255
                     : image->depth() == CV_16U ? 1.0 / 65535
                                                : 1.0);
    return plane;
}

json affineJson(const cv::Matx23d& a) {
    return json::array(
        {json::array({a(0, 0), a(0, 1), a(0, 2)}), json::array({a(1, 0), a(1, 1), a(1, 2)})});
}

/// `p` relative to the result's directory (how result.json names its files, so the folder can
/// be moved as a whole).
std::string relativeToResult(const std::filesystem::path& p, const RegisterRequest& rq) {
    std::error_code e1, e2; // absolute() fails only without a current directory: keep p then
    const auto base = std::filesystem::absolute(rq.output, e1).lexically_normal().parent_path();
    const auto abs = std::filesystem::absolute(p, e2).lexically_normal();
    if (e1 || e2)
        return p.string();
    return abs.lexically_relative(base).string();
}

std::filesystem::path fieldPathOf(const std::filesystem::path& output) {
    return output.parent_path() / (output.stem().string() + ".field.tif");
}

/// The result document (RESULT.json) of a registration; timings are added by the caller.
json resultDocument(const RegisterRequest& rq, const cv::Mat& section, const cv::Mat& labels,
                    const pipeline::Registration& reg, const std::vector<cv::Point2d>& points) {
    json out;
    out["software"] = {{"name", "slicestation"}, {"version", kVersion}};
    out["image"] = {{"path", rq.image.string()},
                    {"file", relativeToResult(rq.image, rq)},
                    {"width", section.cols},
                    {"height", section.rows},
                    {"contrast", reg.contrast == pipeline::Contrast::Brightfield ? "brightfield"
                                                                                 : "fluorescence"}};
    out["atlas"] = {{"path", rq.atlas.string()},
                    {"file", relativeToResult(rq.atlas, rq)},
                    {"width", labels.cols},
                    {"height", labels.rows}};
    if (rq.atlasSlice) {
        AtlasSliceFrame f = *rq.atlasSlice;
        if (!f.stackDir.empty())
            f.stackDir = relativeToResult(f.stackDir, rq);
        out["atlas"]["stack"] = sliceFrameJson(f);
        if (!f.templateFile.empty() && !rq.atlasTemplate)
            out["atlas"]["template"] = f.templateFile;
        if (!f.idsFile.empty() && !rq.atlasIds)
            out["atlas"]["ids"] = f.idsFile;
    }
    if (rq.atlasTemplate)
        out["atlas"]["template"] = relativeToResult(*rq.atlasTemplate, rq);
    if (rq.atlasIds)
        out["atlas"]["ids"] = relativeToResult(*rq.atlasIds, rq);
    const bool ccf = rq.atlasSlice && rq.atlasSlice->ccf;
    out["damaged"] = reg.damaged;
    out["damage_score"] = reg.damageScore;
    out["damage_verdict"] = std::string(pipeline::toString(reg.damageVerdict));
    json regions = json::array();
    for (const pipeline::DamageRegion& d : reg.damage) {
        json poly = json::array();
        for (const cv::Point2f& p : d.polygon)
            poly.push_back({p.x, p.y});
        regions.push_back({{"kind", std::string(pipeline::toString(d.kind))},
                           {"polygon", std::move(poly)},
                           {"area_px", d.areaPx},
                           {"share", d.share},
                           {"length_px", d.lengthPx},
                           {"score", d.score}});
    }
    out["damage_regions"] = std::move(regions);
    out["damage_fraction"] = reg.damageFraction;
    out["damage_summary"] = reg.damageSummary;
    out["affine_atlas_from_image"] = affineJson(reg.affineAtlasFromImage());
    out["mapping"] = mappingJson(savedMapping(reg), fieldPathOf(rq.output).filename().string());
    json pts = json::array();
    for (const cv::Point2d& p : points) {
        const cv::Point2d a = reg.atlasFromImage(p);
        json pt{{"x", p.x}, {"y", p.y}, {"atlas_x", a.x}, {"atlas_y", a.y}};
        if (ccf) {
            const cv::Vec3d c = ccfUm(rq.atlasSlice->geometry, a);
            pt["ccf_um"] = {c[0], c[1], c[2]};
        }
        pts.push_back(std::move(pt));
    }
    out["points"] = std::move(pts);
    const auto& q = reg.quality;
    out["quality"] = {{"correspondences", q.correspondences},
                      {"residual_affine_atlas_px", q.residualAffine},
                      {"residual_final_atlas_px", q.residualFinal},
                      {"atlas_boundary_matched", q.atlasBoundaryMatched},
                      {"section_edges_matched", q.sectionEdgesMatched},
                      {"tissue_overlap", q.tissueOverlap},
                      {"intensity_affine_kept", q.intensityAffineKept},
                      {"intensity_plane_used", q.intensityPlaneUsed},
                      {"intensity_warp_kept", q.intensityWarpKept},
                      {"region_warp_kept", q.regionWarpKept},
                      {"region_warp_left_out", q.regionWarpLeftOut},
                      {"min_jacobian", q.minJacobian},
                      {"fold_repairs", q.foldRepairs},
                      {"fold_repair_nodes", q.foldRepairNodes},
                      {"scale_atlas_px_per_image_px", q.scaleAtlasPxPerImagePx}};
    return out;
}

/// A template plane (given, or the stack slice's own): the registration's atlas intensity (it
/// polishes the affine and, when it explains the section, drives the non-linear stages). Empty
/// when there is none.
core::Result<cv::Mat> atlasIntensityOf(const RegisterRequest& rq, cv::Size labelsSize) {
    if (rq.atlasTemplate)
        return readTemplateImage(*rq.atlasTemplate, labelsSize);
    if (rq.atlasSlice && !rq.atlasSlice->templateFile.empty())
        return readTemplatePlane(rq.atlasSlice->stackDir, rq.atlasSlice->index,
                                 rq.atlasSlice->templateFile, labelsSize);
    return cv::Mat();
}

/// The plane of every atlas id (RegisterRequest::atlasIds, else the stack slice's id plane), CV_32S
/// of the labels' size, or an empty Mat when there is none.
core::Result<cv::Mat> atlasIdsOf(const RegisterRequest& rq, cv::Size labelsSize) {
    std::filesystem::path path;
    std::string what = "atlas ids";
    if (rq.atlasIds) {
        path = *rq.atlasIds;
    } else if (rq.atlasSlice && !rq.atlasSlice->idsFile.empty()) {
        path = std::filesystem::path(rq.atlasSlice->stackDir) / rq.atlasSlice->idsFile;
        what = "stack manifest slices[" + std::to_string(rq.atlasSlice->index) + "].ids";
    } else {
        return cv::Mat();
    }
    auto image = core::readImage(path);
    if (!image)
        return inFile(image.error(), path, what.c_str());
    auto ids = pipeline::labelsFromImage(*image);
    if (!ids)
        return inFile(ids.error(), path, what.c_str());
    if (ids->size() != labelsSize)
        return makeError(ErrorCode::InvalidArgument,
                         what + " " + path.string() + ": " + std::to_string(ids->cols) + " x " +
                             std::to_string(ids->rows) + " px, the atlas labels are " +
                             std::to_string(labelsSize.width) + " x " +
                             std::to_string(labelsSize.height));
    return ids;
}

/// The region warp's labels from the id plane (atlasIdsOf) when the labels do not hold every id
/// themselves (a major-region stack keeps them in a plane of its own: atlas slice --regions
/// major), with the stack's ventricle ids.
core::Result<void> addIdPlane(const RegisterRequest& rq, cv::Size labelsSize,
                              LabelsForRegistration& given) {
    if (!given.regionLabels.empty())
        return {};
    auto ids = atlasIdsOf(rq, labelsSize);
    if (!ids)
        return ids.error();
    if (!ids->empty()) {
        given.regionLabels = *ids;
        if (rq.atlasSlice)
            given.ventricleIds = rq.atlasSlice->ventricleIds;
    }
    return {};
}

} // namespace

core::Result<RegisteredSection> registerSectionFiles(const RegisterRequest& rq,
                                                     const PointsLoader& loadPoints) {
    const auto t0 = Clock::now();
    const double cpu0 = processCpuMs();
    if (auto r = checkPixelSizes(rq); !r)
        return r.error();
    auto atlasImage = core::readImage(rq.atlas);
    if (!atlasImage)
        return inFile(atlasImage.error(), rq.atlas, "atlas");
    auto labels = pipeline::labelsFromImage(*atlasImage);
    if (!labels)
        return inFile(labels.error(), rq.atlas, "atlas");
    if (auto a = checkAtlasLabels(*labels); !a)
        return inFile(a.error(), rq.atlas, "atlas");
    auto section = core::readImage(rq.image);
    if (!section)
        return inFile(section.error(), rq.image, "image");
    if (auto s = checkSectionSize(*section); !s)
        return inFile(s.error(), rq.image, "image");
    std::vector<cv::Point2d> points;
    if (rq.points) {
        if (!loadPoints)
            return makeError(ErrorCode::InvalidArgument,
                             "points: no reader for " + rq.points->string());
        auto p = loadPoints(*rq.points);
        if (!p)
            return p.error();
        points = std::move(*p);
    }
    auto atlasIntensity = atlasIntensityOf(rq, labels->size());
    if (!atlasIntensity)
        return atlasIntensity.error();
    const auto tLoaded = Clock::now();
    const double cpuLoaded = processCpuMs();

    auto given = labelsForRegistration(*labels, rq.stackRegions);
    if (!given)
        return inFile(given.error(), rq.atlas, "atlas");
    if (auto ids = addIdPlane(rq, labels->size(), *given); !ids)
        return ids.error();
    pipeline::RegistrationOptions opt;
    opt.atlasIntensity = *atlasIntensity;
    opt.regionWarp = rq.regionWarp;
    opt.regionLabels = given->regionLabels;
    opt.regionWarpOptions.glassIds = given->ventricleIds;
    opt.imageUmPerPx = rq.imageUmPerPx;
    opt.atlasUmPerPx = rq.atlasUmPerPx;
    opt.workingMaxSide = rq.workingMaxSide;
    opt.maxTurnDeg = rq.maxTurnDeg;
    opt.progress = rq.progress;
    auto reg = pipeline::registerSection(*section, given->labels, opt);
    if (!reg)
        return inFile(reg.error(), rq.image, "image");
    const auto tRegistered = Clock::now();
    const double cpuRegistered = processCpuMs();

    RegisteredSection out{std::move(*reg), section->size(), cv::Mat(), json()};
    out.document = resultDocument(rq, *section, *labels, out.registration, points);
    if (!given->warning.empty())
        out.document["warnings"] = json::array({given->warning});
    if (rq.warpedLabels) {
        out.warpedLabels = out.registration.warpedLabels(*labels, section->size());
        if (auto w = core::writeImage(*rq.warpedLabels, out.warpedLabels); !w)
            return w.error();
    }
    if (rq.overlay) {
        const cv::Mat picture = pipeline::renderOverlay(out.registration, *labels);
        if (auto w = core::writeImage(*rq.overlay, picture); !w)
            return w.error();
    }
    // The full mapping, so that any point can be mapped later without registering again.
    if (auto w = writeMappingField(fieldPathOf(rq.output), savedMapping(out.registration)); !w)
        return w.error();
    const auto tWritten = Clock::now();
    auto ms = [](auto a, auto b) {
        return std::chrono::duration<double, std::milli>(b - a).count();
    };
    json timings = {{"load", ms(t0, tLoaded)}};
    for (const auto& [step, v] : out.registration.timingsMs)
        timings[step == "total" ? "register" : step] = v;
    timings["write"] = ms(tRegistered, tWritten);
    timings["total"] = ms(t0, Clock::now());
    out.document["timings_ms"] = std::move(timings);
    // The same in process CPU time, which a loaded machine does not inflate; "process" also
    // counts the process's start (libraries, static set-up) before this call.
    const double cpuEnd = processCpuMs();
    json cpu = {{"load", cpuLoaded - cpu0}};
    for (const auto& [step, v] : out.registration.cpuMs)
        cpu[step == "total" ? "register" : step] = v;
    cpu["write"] = cpuEnd - cpuRegistered;
    cpu["total"] = cpuEnd - cpu0;
    cpu["process"] = cpuEnd;
    out.document["cpu_timings_ms"] = std::move(cpu);

    if (auto w = core::writeFileAtomically(rq.output, out.document.dump(2) + "\n"); !w)
        return w.error();
    return out;
}

} // namespace slicestation::daemon
