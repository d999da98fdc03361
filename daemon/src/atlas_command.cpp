#include "slicestation/daemon/atlas_command.hpp"

#include "slicestation/core/nrrd.hpp"
#include "slicestation/core/ontology.hpp"
#include "slicestation/daemon/atlas_stack.hpp"
#include "slicestation/pipeline/atlas.hpp"
#include "slicestation/pipeline/atlas_slicing.hpp"

#include <set>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using nlohmann::json;

namespace {

/// Id of the "everything else" region after the major collapse: Allen's "Basic cell groups and
/// regions", so the brain keeps its outline where no major region claims a voxel.
constexpr std::int32_t kOtherId = 8;

} // namespace

core::Result<json> runAtlasSlice(const AtlasSliceRequest& rq) {
    if (rq.regions != "major" && rq.regions != "all")
        return makeError(ErrorCode::InvalidArgument,
                         "--regions must be major or all, not '" + rq.regions + "'");
    if (rq.output.empty()) return makeError(ErrorCode::InvalidArgument, "--output is required");
    json source;
    std::vector<pipeline::AtlasSlice> slices;
    std::vector<StackRegion> regions;

    if (rq.builtin) {
        if (rq.plane != "coronal")
            return makeError(ErrorCode::InvalidArgument,
                             "--plane: the built-in atlas has coronal planes only");
        auto s = builtinStackSlices(rq.intervalUm, rq.firstUm);
        if (!s) return s.error();
        slices = std::move(*s);
        regions = builtinStackRegions();
        source = {{"kind", "builtin"},
                  {"plane", "coronal"},
                  {"interval_um", rq.intervalUm},
                  {"first_um", rq.firstUm},
                  {"length_um", kBuiltinLengthUm}};
    } else {
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
        auto volume = core::readNrrd(rq.volume);
        if (!volume) return volume.error();
        core::Ontology ontology;
        if (!rq.ontology.empty()) {
            auto o = core::readOntologyCsv(rq.ontology);
            if (!o) return o.error();
            ontology = std::move(*o);
        }
        const pipeline::CuttingPlan plan{*orientation,  rq.firstUm, rq.intervalUm,
                                         rq.tiltLrDeg, rq.tiltDvDeg, rq.umPerPx};
        auto cut = pipeline::sliceVolume(*volume, axes, plan);
        if (!cut)
            return makeError(cut.error().code, rq.volume.string() + ": " + cut.error().message);
        slices = std::move(*cut);
        std::set<std::uint32_t> ids;
        if (rq.regions == "major") {
            for (auto& s : slices)
                s.labels = pipeline::collapseLabels(s.labels, ontology, pipeline::majorRegionIds(),
                                                    kOtherId);
            ids.insert(pipeline::majorRegionIds().begin(), pipeline::majorRegionIds().end());
            ids.insert(kOtherId);
        } else {
            for (const auto& s : slices)
                for (auto it = s.labels.begin<int>(); it != s.labels.end<int>(); ++it)
                    if (*it != 0) ids.insert(std::uint32_t(*it));
        }
        for (std::uint32_t id : ids) {
            const core::Structure* st = ontology.find(id);
            regions.push_back(st ? StackRegion{id, st->name, st->acronym, st->colorRgb}
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
    }
    source["um_per_px"] = rq.builtin ? kBuiltinUmPerPx : rq.umPerPx;
    auto stack = writeStack(rq.output, slices, std::move(regions), source);
    if (!stack) return stack.error();
    return json{{"slices", stack->slices.size()},
                {"first_position_um", stack->slices.front().positionUm},
                {"last_position_um", stack->slices.back().positionUm},
                {"regions", stack->regions.size()},
                {"manifest", (rq.output / "manifest.json").string()}};
}

core::Result<json> runAtlasMatch(const AtlasMatchRequest& rq) {
    (void)rq;
    return makeError(ErrorCode::Unsupported, "atlas match is not available yet");
}

} // namespace slicestation::daemon
