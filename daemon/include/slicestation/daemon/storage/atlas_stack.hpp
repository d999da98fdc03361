#pragma once
/// Pre-sliced atlas stacks on disk: a directory of label images (uint32 TIFF, ids as in the
/// atlas) and `manifest.json` describing each slice's plane and the regions.
///
/// manifest.json:
/// ```
/// {"slices": [{"index", "file", "position_um", "normal", "um_per_px",
///              "width", "height", "origin_um", "column_um", "row_um",
///              "template" (optional: the atlas intensity plane, float32 TIFF),
///              "ids" (optional: every atlas id of the plane, uint32 TIFF, when the labels are
///                     collapsed to the major regions)}...],
///  "regions": [{"id", "name", "acronym", "color": "#RRGGBB", "path": [root, ..., id]}...],
///  "ventricle_ids": [...] (optional: the ids of the "ids" planes under the ventricular systems),
///  "source": {"kind": "volume"|"builtin", "plane", "interval_um", ...}}
/// ```
/// Vectors are in the atlas frame: micrometres along (AP, DV, LR) from the centre of the
/// volume's first voxel (pipeline/atlas_slicing.hpp). Blocking file I/O; re-entrant.

#include "slicestation/core/result.hpp"
#include "slicestation/pipeline/atlas_matching.hpp"
#include "slicestation/pipeline/atlas_slicing.hpp"

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

namespace slicestation::daemon {

struct StackRegion {
    std::uint32_t id = 0;
    std::string name, acronym;
    std::uint32_t colorRgb = 0;
    /// The ontology's structure_id_path: ancestors, root first, ending with `id`; empty when
    /// unknown (built-in atlas, stacks written before it was kept).
    std::vector<std::uint32_t> path = {};
};

struct StackSlice {
    int index = 0;
    std::string file; ///< relative to the stack directory
    double positionUm = 0;
    double umPerPx = 0;
    pipeline::SliceGeometry geometry;
    /// The slice's atlas intensity plane (float32 TIFF of the slice's size, e.g. the Allen
    /// average template cut along the same plane), relative to the stack directory; empty =
    /// none (stacks written without --template).
    std::string templateFile = {};
    /// The slice's plane of every atlas id (uint32 TIFF of the slice's size) when `file` holds
    /// the ids collapsed to the major regions, relative to the stack directory: the
    /// registration's region warp fits every region the section's stain shows while results
    /// keep the major regions. Empty = none (`file` holds the ids as the volume has them, or a
    /// stack written before these planes were kept).
    std::string idsFile = {};
};

struct AtlasStack {
    std::filesystem::path dir;
    std::vector<StackSlice> slices; ///< in index order, index == position in the vector
    std::vector<StackRegion> regions;
    nlohmann::json source;
    /// The ids of the slices' id planes (StackSlice::idsFile) under the ventricular systems
    /// (73): the region warp paints them as glass.
    std::vector<std::int32_t> ventricleIds = {};
};

/// The stack's region with this id, or null (0 and ids the ontology lacks).
const StackRegion* findRegion(const AtlasStack& stack, std::uint32_t id) noexcept;

/// "#RRGGBB", as the manifest writes a region's colour.
std::string colorHex(std::uint32_t rgb);

/// Writes every slice as `slice-NNN.tif` (with `template-NNN.tif` and `ids-NNN.tif` when the
/// slice has an intensity plane or id plane) and then `manifest.json` (atomically, last, so a
/// reader never sees a manifest naming a missing file). Creates `dir` when needed.
/// `ventricleIds`: AtlasStack::ventricleIds.
/// \return IoError / NotFound from the file layer, InvalidArgument for an empty stack or a
///         template or id plane not of the slice's size and type.
[[nodiscard]] core::Result<AtlasStack> writeStack(const std::filesystem::path& dir,
                                                  const std::vector<pipeline::AtlasSlice>& slices,
                                                  std::vector<StackRegion> regions,
                                                  nlohmann::json source,
                                                  std::vector<std::int32_t> ventricleIds = {});

/// Reads `dir/manifest.json` (or the manifest file itself when given one).
/// \return NotFound (no manifest), IoError, InvalidArgument (malformed JSON or a field missing or
///         of the wrong type: the message names the manifest and the field).
[[nodiscard]] core::Result<AtlasStack> readStack(const std::filesystem::path& dirOrManifest);

/// The labels of slice `index`, CV_32S. \return OutOfRange (no such index), the errors of
/// core::readImage, InvalidArgument (not a label image).
[[nodiscard]] core::Result<cv::Mat> readStackSlice(const AtlasStack& stack, int index);

/// The atlas intensity plane of slice `index` (CV_32F, the slice's size), or an empty Mat when
/// the stack holds none for it. \return OutOfRange (no such index), the errors of
/// core::readImage, InvalidArgument (not a one-channel float image of the slice's size); every
/// message names the manifest entry (slices[i].template) and the file.
[[nodiscard]] core::Result<cv::Mat> readStackTemplate(const AtlasStack& stack, int index);
/// readStackTemplate for slice `index` of the stack at `dir` whose manifest names `file` (not
/// empty) and gives the slice `size` (an empty size is not checked).
[[nodiscard]] core::Result<cv::Mat> readTemplatePlane(const std::filesystem::path& dir, int index,
                                                      const std::string& file, cv::Size size);

/// Path of slice `index`'s label image. \return OutOfRange for an unknown index.
[[nodiscard]] core::Result<std::filesystem::path> stackSlicePath(const AtlasStack& stack,
                                                                 int index);

/// Length of the built-in brain from the front (apFraction 0) to the back (1), micrometres.
inline constexpr double kBuiltinLengthUm = 8000;
/// Pixel size of built-in planes at their default size (456 x 320 px).
inline constexpr double kBuiltinUmPerPx = 25;

/// The built-in procedural atlas (sim::builtinAtlasPlane) cut every `intervalUm` from
/// `firstUm` over kBuiltinLengthUm, with its regions. InvalidArgument for a bad interval,
/// OutOfRange for firstUm outside the brain.
[[nodiscard]] core::Result<std::vector<pipeline::AtlasSlice>> builtinStackSlices(double intervalUm,
                                                                                 double firstUm);
std::vector<StackRegion> builtinStackRegions();

/// Matching features of every slice of `stack` (read from disk), one working pixel size.
[[nodiscard]] core::Result<std::vector<pipeline::SliceFeatures>>
stackFeatures(const AtlasStack& stack);

} // namespace slicestation::daemon
