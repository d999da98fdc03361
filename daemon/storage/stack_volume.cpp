#include "slicestation/daemon/storage/stack_volume.hpp"

#include "slicestation/pipeline/atlas.hpp"

#include <algorithm>

namespace slicestation::daemon {

using core::ErrorCode;
using core::makeError;
using nlohmann::json;
namespace fs = std::filesystem;

fs::path manifestSourcePath(const AtlasStack& stack, const std::string& key) {
    const std::string given =
        stack.source.is_object() ? stack.source.value(key, std::string()) : std::string();
    if (given.empty())
        return {};
    const fs::path p(given);
    std::error_code e1, e2;
    if (p.is_relative() && !fs::exists(p, e1) && fs::exists(stack.dir / p, e2))
        return stack.dir / p;
    return p;
}

core::Result<IntensityVolume> readIntensityVolume(const fs::path& path, const core::Volume& labels,
                                                  pipeline::VolumeAxes axes,
                                                  const std::string& what) {
    auto read = core::readNrrd(path);
    if (!read)
        return read.error();
    auto offset = pipeline::intensityFrameOffsetUm(labels, axes, *read, axes);
    if (!offset)
        return makeError(offset.error().code,
                         what + " " + path.string() + ": " + offset.error().message);
    const std::uint32_t top = *std::max_element(read->data.begin(), read->data.end());
    if (top == 0)
        return makeError(ErrorCode::InvalidArgument,
                         what + " " + path.string() + ": every voxel is 0");
    return IntensityVolume{std::move(*read), *offset, double(top)};
}

namespace {

/// The template volume of a stack with template planes, cut as `atlas slice --template` cut it.
core::Result<void> readTemplateVolume(const AtlasStack& stack, StackVolume& v) {
    const bool hasPlanes = std::any_of(stack.slices.begin(), stack.slices.end(),
                                       [](const StackSlice& s) { return !s.templateFile.empty(); });
    if (!hasPlanes)
        return {};
    const fs::path path = manifestSourcePath(stack, "template");
    if (path.empty())
        return makeError(ErrorCode::InvalidArgument,
                         stack.dir.string() +
                             ": the slices have template planes but the manifest names no "
                             "template volume (source.template)");
    auto templ = readIntensityVolume(path, v.volume, v.axes, "template volume");
    if (!templ)
        return templ.error();
    v.templateVolume = std::move(*templ);
    return {};
}

} // namespace

namespace {

core::Result<StackVolume> readVolumeOf(const AtlasStack& stack, const fs::path& volume,
                                       const fs::path& ontology, bool templates) {
    const json& src = stack.source;
    if (!src.is_object() || src.value("kind", std::string()) != "volume")
        return makeError(ErrorCode::InvalidArgument,
                         "tilted planes need a stack cut from a volume (atlas slice --volume); " +
                             stack.dir.string() + " is not");
    if (stack.slices.empty())
        return makeError(ErrorCode::InvalidArgument, stack.dir.string() + ": empty stack");
    StackVolume v;
    v.path = volume.empty() ? manifestSourcePath(stack, "volume") : volume;
    if (v.path.empty())
        return makeError(ErrorCode::InvalidArgument,
                         stack.dir.string() + ": the manifest names no volume (source.volume)");
    v.axes = src.value("axes", std::string()) == "quicknii" ? pipeline::VolumeAxes::QuickNii
                                                            : pipeline::VolumeAxes::Allen;
    auto orientation = pipeline::parsePlaneOrientation(src.value("plane", std::string()));
    if (!orientation)
        return makeError(ErrorCode::InvalidArgument,
                         stack.dir.string() +
                             ": manifest source.plane: " + orientation.error().message);
    v.orientation = *orientation;
    v.major = src.value("regions", std::string("major")) == "major";
    v.umPerPx = stack.slices.front().umPerPx;
    auto read = core::readNrrd(v.path);
    if (!read)
        return makeError(read.error().code,
                         "volume " + v.path.string() + ": " + read.error().message);
    if (!src.contains("volume_sizes") || src["volume_sizes"] != json(read->sizes))
        return makeError(ErrorCode::InvalidArgument,
                         "volume " + v.path.string() +
                             ": its size differs from the volume the stack was cut from");
    v.volume = std::move(*read);
    if (v.major) {
        const fs::path o = ontology.empty() ? manifestSourcePath(stack, "ontology") : ontology;
        auto onto = core::readOntologyCsvIfGiven(o);
        if (!onto)
            return makeError(onto.error().code,
                             "ontology " + o.string() + ": " + onto.error().message);
        if (onto->structures().empty())
            return makeError(ErrorCode::InvalidArgument,
                             stack.dir.string() +
                                 ": a major-region stack needs its ontology to cut planes "
                                 "(source.ontology)");
        v.ontology = std::move(*onto);
    }
    if (templates)
        if (auto t = readTemplateVolume(stack, v); !t)
            return t.error();
    return v;
}

} // namespace

core::Result<StackVolume> readStackVolume(const AtlasStack& stack, const fs::path& volume,
                                          const fs::path& ontology, bool templates) {
    try {
        return readVolumeOf(stack, volume, ontology, templates);
    } catch (const json::exception& e) {
        // A manifest field of the wrong type (readStack checks the slices, not the source).
        return makeError(ErrorCode::InvalidArgument,
                         stack.dir.string() + ": manifest source: " + e.what());
    }
}

namespace {

/// The plane's geometry and labels (collapsed as the stack's), without the template.
core::Result<pipeline::AtlasSlice> planeLabels(const StackVolume& v, double positionUm,
                                               double tiltLrDeg, double tiltDvDeg) {
    auto g = pipeline::planeGeometry(v.volume, v.axes,
                                     {v.orientation, positionUm, tiltLrDeg, tiltDvDeg, v.umPerPx});
    if (!g)
        return g.error();
    auto labels = pipeline::sampleLabels(v.volume, v.axes, *g);
    if (!labels)
        return labels.error();
    pipeline::AtlasSlice s;
    s.geometry = *g;
    if (v.major) {
        s.ids = *labels; // every id, for the registration's region warp (AtlasSlice::ids)
        s.labels = pipeline::collapseLabels(*labels, v.ontology, pipeline::majorRegionIds(),
                                            pipeline::kOtherRegionId);
    } else {
        s.labels = std::move(*labels);
    }
    return s;
}

} // namespace

core::Result<pipeline::AtlasSlice> cutStackPlane(const StackVolume& v, double positionUm,
                                                 double tiltLrDeg, double tiltDvDeg) {
    auto s = planeLabels(v, positionUm, tiltLrDeg, tiltDvDeg);
    if (s && v.templateVolume)
        s->intensity =
            pipeline::sampleIntensity(v.templateVolume->volume, v.axes, s->geometry,
                                      v.templateVolume->offsetUm, v.templateVolume->scale);
    return s;
}

core::Result<pipeline::SliceFeatures> stackPlaneFeatures(const StackVolume& v, double positionUm,
                                                         double tiltLrDeg, double tiltDvDeg,
                                                         double workUmPerPx) {
    auto s = planeLabels(v, positionUm, tiltLrDeg, tiltDvDeg);
    if (!s)
        return s.error();
    return pipeline::sliceFeatures(s->labels, v.umPerPx, positionUm, workUmPerPx);
}

} // namespace slicestation::daemon
