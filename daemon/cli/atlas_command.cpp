#include "slicestation/daemon/cli/atlas_command.hpp"

#include "slicestation/core/atomic_file.hpp"

#include "slicestation/core/image_file.hpp"
#include "slicestation/core/nrrd.hpp"
#include "slicestation/core/ontology.hpp"
#include "slicestation/daemon/cli/register_command.hpp"
#include "slicestation/daemon/storage/atlas_stack.hpp"
#include "slicestation/daemon/storage/stack_volume.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/pipeline/atlas_matching.hpp"
#include "slicestation/pipeline/atlas_slicing.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>

#include <set>
#include <sstream>
#include <tuple>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using nlohmann::json;

namespace {

void report(const AtlasSliceRequest& rq, const char* phase, int done, int total) {
    if (rq.progress)
        rq.progress(phase, done, total);
}

/// InvalidArgument naming `option` unless `value` is finite and within [min, max].
core::Result<void> checkRange(const char* option, double value, double min, double max) {
    if (std::isfinite(value) && value >= min && value <= max)
        return {};
    std::ostringstream os;
    os << option << " " << value << " is not a finite number in [" << min << ", " << max << "]";
    return makeError(ErrorCode::InvalidArgument, os.str());
}

/// The ids a stack's manifest lists, after collapsing the slices to the major regions when asked
/// (each slice then keeps every id in AtlasSlice::ids, and `ventricleIds` gets the ventricles'
/// ids among them) or with every ancestor of the ids the slices show.
std::set<std::uint32_t> stackIds(const AtlasSliceRequest& rq, const core::Ontology& ontology,
                                 std::vector<pipeline::AtlasSlice>& slices,
                                 std::vector<std::int32_t>& ventricleIds) {
    std::set<std::int32_t> seen;
    for (const auto& s : slices)
        pipeline::collectIds(s.labels, seen);
    std::set<std::uint32_t> ids;
    if (rq.regions == "major") {
        // Results name the major regions; the registration's region warp still fits every id
        // the section's stain shows (docs/atlas.md), so each slice keeps them in a plane of
        // its own, and the stack the ids of its ventricles (painted as glass).
        const int n = static_cast<int>(slices.size());
        for (int i = 0; i < n; ++i) {
            report(rq, "collapsing regions", i, n);
            auto& s = slices[static_cast<std::size_t>(i)];
            s.ids = s.labels;
            s.labels = pipeline::collapseLabels(s.ids, ontology, pipeline::majorRegionIds(),
                                                pipeline::kOtherRegionId);
        }
        ventricleIds = pipeline::idsUnder(seen, ontology, pipeline::kVentricularSystemsId);
        ids.insert(pipeline::majorRegionIds().begin(), pipeline::majorRegionIds().end());
        ids.insert(pipeline::kOtherRegionId);
    } else {
        for (std::int32_t id : seen)
            ids.insert(std::uint32_t(id));
        // Every ancestor too, so that counts and exports can be rolled up the whole hierarchy
        // with names (docs/results.md).
        std::set<std::uint32_t> ancestors;
        for (std::uint32_t id : ids)
            if (const core::Structure* st = ontology.find(id))
                ancestors.insert(st->path.begin(), st->path.end());
        ids.insert(ancestors.begin(), ancestors.end());
    }
    return ids;
}

/// runAtlasSlice from a volume file (NRRD) and its ontology: the slices, their regions and the
/// source description of the manifest.
core::Result<void> sliceVolumeFile(const AtlasSliceRequest& rq,
                                   std::vector<pipeline::AtlasSlice>& slices,
                                   std::vector<StackRegion>& regions, json& source,
                                   std::vector<std::int32_t>& ventricleIds) {
    if (rq.volume.empty())
        return makeError(ErrorCode::InvalidArgument, "--volume is required (or --builtin)");
    pipeline::VolumeAxes axes;
    if (rq.axes == "allen")
        axes = pipeline::VolumeAxes::Allen;
    else if (rq.axes == "quicknii")
        axes = pipeline::VolumeAxes::QuickNii;
    else
        return makeError(ErrorCode::InvalidArgument,
                         "--axes must be allen or quicknii, not '" + rq.axes + "'");
    auto orientation = pipeline::parsePlaneOrientation(rq.plane);
    if (!orientation)
        return makeError(ErrorCode::InvalidArgument, "--plane: " + orientation.error().message);
    if (rq.regions == "major" && rq.ontology.empty())
        return makeError(ErrorCode::InvalidArgument,
                         "--regions major needs --ontology (structure_id_path)");
    report(rq, "reading the volume", 0, 0);
    auto volume = core::readNrrd(rq.volume);
    if (!volume)
        return volume.error();
    auto ontologyRead = core::readOntologyCsvIfGiven(rq.ontology);
    if (!ontologyRead)
        return ontologyRead.error();
    const core::Ontology& ontology = *ontologyRead;
    const pipeline::CuttingPlan plan{*orientation, rq.firstUm,   rq.intervalUm,
                                     rq.tiltLrDeg, rq.tiltDvDeg, rq.umPerPx};
    report(rq, "cutting slices", 0, 0);
    auto cut = pipeline::sliceVolume(*volume, axes, plan, [&rq](int done, int total) {
        report(rq, "cutting slices", done, total);
    });
    if (!cut)
        return makeError(cut.error().code, rq.volume.string() + ": " + cut.error().message);
    slices = std::move(*cut);
    if (!rq.templateVolume.empty()) {
        report(rq, "cutting the template", 0, 0);
        auto templ = readIntensityVolume(rq.templateVolume, *volume, axes, "--template");
        if (!templ)
            return templ.error();
        for (auto& s : slices)
            s.intensity = pipeline::sampleIntensity(templ->volume, axes, s.geometry,
                                                    templ->offsetUm, templ->scale);
    }
    const std::set<std::uint32_t> ids = stackIds(rq, ontology, slices, ventricleIds);
    for (std::uint32_t id : ids) {
        const core::Structure* st = ontology.find(id);
        regions.push_back(st ? StackRegion{id, st->name, st->acronym, st->colorRgb, st->path}
                             : StackRegion{id, "", "", 0});
    }
    const cv::Vec3d extent = pipeline::volumeExtentUm(*volume, axes);
    source = {{"kind", "volume"},
              {"volume", rq.volume.string()},
              {"ontology", rq.ontology.string()},
              {"axes", rq.axes},
              {"volume_sizes", volume->sizes},
              {"volume_spacing_um", volume->spacingUm},
              {"extent_um", {extent[0], extent[1], extent[2]}},
              {"plane", rq.plane},
              {"interval_um", rq.intervalUm},
              {"first_um", rq.firstUm},
              {"tilt_lr_deg", rq.tiltLrDeg},
              {"tilt_dv_deg", rq.tiltDvDeg},
              {"regions", rq.regions}};
    if (!rq.templateVolume.empty())
        source["template"] = rq.templateVolume.string();
    return {};
}

} // namespace

core::Result<json> runAtlasSlice(const AtlasSliceRequest& rq) {
    for (const auto& [option, value, min, max] :
         {std::tuple{"--interval-um", rq.intervalUm, kMinIntervalUm, kMaxIntervalUm},
          std::tuple{"--first-um", rq.firstUm, -kMaxPositionUm, kMaxPositionUm},
          std::tuple{"--tilt-lr-deg", rq.tiltLrDeg, -kMaxTiltDeg, kMaxTiltDeg},
          std::tuple{"--tilt-dv-deg", rq.tiltDvDeg, -kMaxTiltDeg, kMaxTiltDeg},
          std::tuple{"--um-per-px", rq.umPerPx, kMinSliceUmPerPx, kMaxUmPerPx}})
        if (auto r = checkRange(option, value, min, max); !r)
            return r.error();
    if (rq.regions != "major" && rq.regions != "all")
        return makeError(ErrorCode::InvalidArgument,
                         "--regions must be major or all, not '" + rq.regions + "'");
    if (rq.output.empty())
        return makeError(ErrorCode::InvalidArgument, "--output is required");
    json source;
    std::vector<pipeline::AtlasSlice> slices;
    std::vector<StackRegion> regions;
    std::vector<std::int32_t> ventricleIds;

    if (rq.builtin) {
        if (rq.plane != "coronal")
            return makeError(ErrorCode::InvalidArgument,
                             "--plane: the built-in atlas has coronal planes only");
        if (!rq.templateVolume.empty())
            return makeError(ErrorCode::InvalidArgument,
                             "--template: the built-in atlas has no intensity volume");
        auto s = builtinStackSlices(rq.intervalUm, rq.firstUm);
        if (!s)
            return s.error();
        slices = std::move(*s);
        regions = builtinStackRegions();
        source = {{"kind", "builtin"},
                  {"plane", "coronal"},
                  {"interval_um", rq.intervalUm},
                  {"first_um", rq.firstUm},
                  {"length_um", kBuiltinLengthUm}};
    } else if (auto r = sliceVolumeFile(rq, slices, regions, source, ventricleIds); !r) {
        return r.error();
    }
    source["um_per_px"] = rq.builtin ? kBuiltinUmPerPx : rq.umPerPx;
    report(rq, "writing the stack", 0, 0);
    auto stack = writeStack(rq.output, slices, std::move(regions), source, std::move(ventricleIds));
    if (!stack)
        return stack.error();
    return json{{"slices", stack->slices.size()},
                {"first_position_um", stack->slices.front().positionUm},
                {"last_position_um", stack->slices.back().positionUm},
                {"regions", stack->regions.size()},
                {"manifest", (rq.output / "manifest.json").string()}};
}

core::Result<void> useStackSlice(RegisterRequest& rq, int slice) {
    namespace fs = std::filesystem;
    const bool isStack = fs::is_directory(rq.atlas) || rq.atlas.filename() == "manifest.json";
    if (!isStack) {
        if (slice >= 0)
            return makeError(ErrorCode::InvalidArgument,
                             "--slice needs --atlas to be a stack directory, not " +
                                 rq.atlas.string());
        return {};
    }
    if (slice < 0)
        return makeError(ErrorCode::InvalidArgument,
                         "--atlas " + rq.atlas.string() + " is a stack: choose one with --slice N");
    auto stack = readStack(rq.atlas);
    if (!stack)
        return stack.error();
    auto path = stackSlicePath(*stack, slice);
    if (!path)
        return path.error();
    rq.atlas = *path;
    rq.atlasSlice = sliceFrame(*stack, slice);
    rq.stackRegions = stack->regions;
    if (rq.imageUmPerPx > 0 && rq.atlasUmPerPx <= 0)
        rq.atlasUmPerPx = stack->slices[size_t(slice)].umPerPx;
    return {};
}

core::Result<void> useOntology(RegisterRequest& rq, const std::filesystem::path& ontology) {
    if (rq.atlasSlice)
        return makeError(ErrorCode::InvalidArgument,
                         "--ontology is for a label image: the stack's manifest names its regions");
    auto read = core::readOntologyCsv(ontology);
    if (!read)
        return makeError(read.error().code,
                         "--ontology " + ontology.string() + ": " + read.error().message);
    rq.stackRegions.clear();
    for (const core::Structure& st : read->structures())
        rq.stackRegions.push_back({st.id, st.name, st.acronym, st.colorRgb, st.path});
    return {};
}

core::Result<json> runAtlasMatch(const AtlasMatchRequest& rq) {
    using Clock = std::chrono::steady_clock;
    const auto t0 = Clock::now();
    if (rq.window < 0)
        return makeError(ErrorCode::InvalidArgument, "--window must be >= 0");
    if (rq.imageUmPerPx != 0)
        if (auto r = checkRange("--image-um-per-px", rq.imageUmPerPx, kMinUmPerPx, kMaxUmPerPx); !r)
            return r.error();
    auto stack = readStack(rq.stack);
    if (!stack)
        return stack.error();
    const int count = int(stack->slices.size());
    if (rq.expectedIndex && (*rq.expectedIndex < 0 || *rq.expectedIndex >= count))
        return makeError(ErrorCode::OutOfRange,
                         "--expected-index " + std::to_string(*rq.expectedIndex) +
                             " is not in the stack (0.." + std::to_string(count - 1) + ")");
    auto image = core::readImage(rq.image);
    if (!image)
        return image.error();
    if (rq.progress)
        rq.progress("reading the stack's slices", 0, 0);
    auto features = stackFeatures(*stack);
    if (!features)
        return features.error();
    const auto tLoaded = Clock::now();

    pipeline::MatchOptions opt;
    if (rq.progress)
        opt.progress = [&rq](int done, int total) {
            rq.progress("matching against the slices", done, total);
        };
    if (rq.expectedIndex) {
        // A window wider than the stack searches all of it; bounded first, so that no sum
        // overflows (expectedIndex < count).
        const int window = std::min(rq.window, count);
        opt.first = std::max(0, *rq.expectedIndex - window);
        opt.last = std::min(count - 1, *rq.expectedIndex + window);
    }
    auto section =
        pipeline::sectionFeatures(*image, rq.imageUmPerPx, features->front().workUmPerPx);
    if (!section)
        return makeError(section.error().code, rq.image.string() + ": " + section.error().message);
    auto m = pipeline::matchSection(*section, *features, opt);
    if (!m)
        return makeError(m.error().code, rq.image.string() + ": " + m.error().message);
    const auto tMatched = Clock::now();

    json candidates = json::array();
    for (const auto& c : m->candidates)
        candidates.push_back({{"index", c.index},
                              {"position_um", stack->slices[size_t(c.index)].positionUm},
                              {"score", c.score},
                              {"overlap", c.overlap}});
    auto ms = [](auto a, auto b) {
        return std::chrono::duration<double, std::milli>(b - a).count();
    };
    json out = {{"index", m->index},
                {"position_um", m->positionUm},
                {"slice_position_um", stack->slices[size_t(m->index)].positionUm},
                {"score", m->score},
                {"tilt_lr_deg", m->tiltColumnsDeg},
                {"tilt_dv_deg", m->tiltRowsDeg},
                {"tilt_estimated", m->tiltEstimated},
                {"candidates", std::move(candidates)},
                {"stack", stack->dir.string()},
                {"image", rq.image.string()},
                {"timings_ms",
                 {{"load", ms(t0, tLoaded)},
                  {"match", ms(tLoaded, tMatched)},
                  {"total", ms(t0, Clock::now())}}}};
    if (rq.expectedIndex) {
        out["expected_index"] = *rq.expectedIndex;
        // More than one slice off: the plan and the section disagree (sections mounted out of
        // order, skipped or tilted); the caller decides whether that is a warning.
        out["mismatch"] = std::abs(m->index - *rq.expectedIndex) > 1;
    }
    if (auto w = core::writeFileAtomically(rq.output, out.dump(2) + "\n"); !w)
        return w.error();
    return out;
}

} // namespace slicestation::daemon
