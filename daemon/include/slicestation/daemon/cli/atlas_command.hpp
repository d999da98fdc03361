#pragma once
/// `slicectl atlas slice` and `slicectl atlas match`: pre-slicing a 3-D atlas for a cutting plan,
/// and finding the stack slice a section came from.

#include "slicestation/core/result.hpp"
#include "slicestation/daemon/cli/register_command.hpp"
#include "slicestation/daemon/storage/atlas_stack.hpp"
#include "slicestation/pipeline/atlas_matching.hpp"

#include <nlohmann/json.hpp>

#include <filesystem>
#include <functional>
#include <optional>
#include <string>
#include <vector>

namespace slicestation::daemon {

/// Accepted ranges of an atlas slice request (checked by runAtlasSlice and by slicectl).
inline constexpr double kMinIntervalUm = 1;
inline constexpr double kMaxIntervalUm = 20000;
inline constexpr double kMaxPositionUm = 100000; ///< |first_um|
inline constexpr double kMaxTiltDeg = 60;
inline constexpr double kMinSliceUmPerPx = 1; ///< finer than any atlas voxel
// kMaxUmPerPx (register_command.hpp) bounds the slice pixel size from above.

struct AtlasSliceRequest {
    bool builtin = false;           ///< the procedural built-in atlas, no files needed
    std::filesystem::path volume;   ///< annotation NRRD (uint16/uint32 ids)
    std::filesystem::path ontology; ///< structure_tree_safe_2017.csv; needed for "major"
    std::string axes = "allen";     ///< allen | quicknii
    std::string plane = "coronal";  ///< coronal | sagittal | horizontal
    double intervalUm = 100;
    double firstUm = 0;
    double tiltLrDeg = 0; ///< the normal leans toward the image columns (coronal: LR)
    double tiltDvDeg = 0; ///< the normal leans toward the image rows (coronal: DV)
    double umPerPx = 25;
    std::string regions = "major"; ///< major | all
    /// Optional intensity volume of the same space (e.g. average_template_100.nrrd, the same
    /// axis convention as `volume`): every plane is cut from it too (trilinear, divided by the
    /// volume's largest value) and stored beside its labels as the slice's atlas intensity.
    std::filesystem::path templateVolume;
    std::filesystem::path output; ///< stack directory
    /// Told each phase ("reading the volume", "cutting slices", "collapsing regions", "writing
    /// the stack") with done/total (total 0: not counted); may be empty.
    std::function<void(const std::string& phase, int done, int total)> progress;
};

/// Reads the volume and ontology, cuts the plan, collapses regions, writes the stack.
/// Ranges: interval [kMinIntervalUm, kMaxIntervalUm], first_um within +-kMaxPositionUm, tilts
/// within +-kMaxTiltDeg, um_per_px [kMinSliceUmPerPx, kMaxUmPerPx], all finite; the whole stack
/// within pipeline::checkStackBudget.
/// \return a summary (slice count, positions); InvalidArgument naming the option or file,
///         NotFound, IoError, Unsupported (volume type), OutOfRange (plane outside the volume).
[[nodiscard]] core::Result<nlohmann::json> runAtlasSlice(const AtlasSliceRequest& request);

struct AtlasMatchRequest {
    std::filesystem::path stack; ///< stack directory or its manifest.json
    std::filesystem::path image; ///< section image
    std::optional<int> expectedIndex;
    int window = 5;               ///< slices either side of expectedIndex to search, >= 0
    double imageUmPerPx = 0;      ///< 0 = unknown: the scale is then found per slice
    std::filesystem::path output; ///< MATCH.json
    /// Progress for a bar: phase "features" (done, total slices; total 0 while unknown), then
    /// "matching" (candidates done of total, pipeline::MatchOptions::progress). May be empty.
    std::function<void(const std::string& phase, int done, int total)> progress;
};

/// Matches the section against the stack (pipeline::matchSection) and writes MATCH.json:
/// {"index", "position_um" (refined between slices), "slice_position_um", "score",
///  "tilt_lr_deg", "tilt_dv_deg", "tilt_estimated",
///  "candidates": [{"index", "position_um", "score", "overlap"}...] best first, "timings_ms",
///  and with an expected index "expected_index" and "mismatch" (more than one slice off)}.
/// \return NotFound / IoError / InvalidArgument for the files, OutOfRange for an expected index
///         outside the stack, NoTissue.
[[nodiscard]] core::Result<nlohmann::json> runAtlasMatch(const AtlasMatchRequest& request);

/// `slicectl register --atlas STACK_DIR --slice N`: when `request.atlas` is a stack directory
/// (or its manifest.json), points it at slice `slice`'s label image and, when the section's pixel
/// size is given, fills in the slice's. A plain image with slice < 0 is left alone.
/// \return InvalidArgument (--slice without a stack, a stack without --slice), OutOfRange, the
///         errors of readStack.
[[nodiscard]] core::Result<void> useStackSlice(RegisterRequest& request, int slice);

/// `slicectl register --atlas LABELS --ontology CSV`: a label image of Allen ids (not a stack)
/// named by the ontology (structure_id_path), so that it is registered as a slice of a stack cut
/// `--regions all` is (RegisterRequest::stackRegions: the major regions for the geometric stages
/// and the damage check, every id for the region warp, the ventricles known).
/// \return InvalidArgument (the atlas is a stack: its manifest names its regions), the errors of
///         core::readOntologyCsv naming the file.
[[nodiscard]] core::Result<void> useOntology(RegisterRequest& request,
                                             const std::filesystem::path& ontology);

} // namespace slicestation::daemon
