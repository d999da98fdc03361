#pragma once
/// The volume a stack was cut from, read back to cut the planes the stack does not hold: tilted
/// ones at any position (issue 19: the brain's cutting angle, `slicectl atlas match-series
/// --tilt-search` and the daemon's tilted planes, docs/atlas.md). Planes are cut exactly as
/// `slicectl atlas slice` cut the stack's: same axes, orientation, pixel size, region set (the
/// major collapse when the stack has it) and, when the stack has template planes, the template
/// volume cut along the same plane.
///
/// Blocking file I/O (a volume of 10-300 MB); cutting a plane is re-entrant (const).
#include "slicestation/core/nrrd.hpp"
#include "slicestation/core/ontology.hpp"
#include "slicestation/core/result.hpp"
#include "slicestation/daemon/storage/atlas_stack.hpp"
#include "slicestation/pipeline/atlas_matching.hpp"
#include "slicestation/pipeline/atlas_slicing.hpp"

#include <filesystem>
#include <optional>

namespace slicestation::daemon {

/// An intensity volume (e.g. the Allen average template) ready to be cut along the planes of a
/// label volume: where the labels' frame lies in it and the divisor that maps it to [0, 1].
struct IntensityVolume {
    core::Volume volume;
    cv::Vec3d offsetUm{0, 0, 0}; ///< pipeline::intensityFrameOffsetUm
    double scale = 1;            ///< its largest value
};

/// Reads `path` to be cut beside `labels` (same axes). \return the errors of core::readNrrd
/// (naming the file); InvalidArgument "`what` PATH: ..." when the two volumes' extents differ
/// (pipeline::intensityFrameOffsetUm) or every voxel is 0.
[[nodiscard]] core::Result<IntensityVolume> readIntensityVolume(const std::filesystem::path& path,
                                                                const core::Volume& labels,
                                                                pipeline::VolumeAxes axes,
                                                                const std::string& what);

struct StackVolume {
    std::filesystem::path path; ///< the label volume read
    core::Volume volume;
    core::Ontology ontology; ///< for the major collapse; empty for `--regions all` stacks
    pipeline::VolumeAxes axes = pipeline::VolumeAxes::Allen;
    pipeline::PlaneOrientation orientation = pipeline::PlaneOrientation::Coronal;
    bool major = true; ///< the stack's labels were collapsed to the major regions
    double umPerPx = 0;
    /// The template volume when the stack has template planes; empty without one.
    std::optional<IntensityVolume> templateVolume;
};

/// A file the manifest's `source` names under `key`: as written, or else relative to the stack
/// directory when the stack was cut with a relative path from elsewhere. Empty when not named.
std::filesystem::path manifestSourcePath(const AtlasStack& stack, const std::string& key);

/// Reads the volume `stack` was cut from (`volume`, else the manifest's source.volume), its
/// ontology for a major-region stack (`ontology`, else source.ontology) and, with `templates`
/// when the stack's slices have template planes, the template volume (source.template).
/// \return InvalidArgument (the stack was not cut from a volume, the manifest names no volume,
///         the volume's sizes differ from source.volume_sizes, a major-region stack without an
///         ontology, a template-plane stack whose manifest names no template volume), the errors
///         of core::readNrrd and core::readOntologyCsvIfGiven; every message names the file.
[[nodiscard]] core::Result<StackVolume> readStackVolume(const AtlasStack& stack,
                                                        const std::filesystem::path& volume = {},
                                                        const std::filesystem::path& ontology = {},
                                                        bool templates = true);

/// The plane at `positionUm` (along the untilted normal, as the stack's slices) leaned by the
/// two tilts (degrees, as `atlas slice --tilt-lr-deg/--tilt-dv-deg`): labels as the stack's,
/// geometry, and the template plane when the volume has one.
/// \return the errors of pipeline::planeGeometry (OutOfRange: the plane misses the volume) and
///         pipeline::sampleLabels.
[[nodiscard]] core::Result<pipeline::AtlasSlice>
cutStackPlane(const StackVolume& v, double positionUm, double tiltLrDeg, double tiltDvDeg);

/// The matching features of such a plane's labels at working pixel size `workUmPerPx`
/// (pipeline::PlaneFeatures for searchSeriesTilt; no template is cut).
[[nodiscard]] core::Result<pipeline::SliceFeatures>
stackPlaneFeatures(const StackVolume& v, double positionUm, double tiltLrDeg, double tiltDvDeg,
                   double workUmPerPx);

} // namespace slicestation::daemon
