#pragma once
/// A registered section's results in forms other tools take (docs/results.md): the full mapping
/// saved beside result.json (affine + displacement field TIFF) and read back, atlas points in
/// CCFv3 micrometres, QuickNII/VisuAlign slices (anchoring + markers) and QuPath GeoJSON.
///
/// Coordinates: section and atlas pixels have their centres at integers (origin top-left, x
/// right, y down), as pipeline::Registration. QuickNII/VisuAlign and QuPath measure from the
/// image's top-left corner (a pixel's centre at +0.5); the conversions are in these functions.
/// Blocking file I/O; re-entrant.

#include "slicestation/core/result.hpp"
#include "slicestation/daemon/storage/atlas_stack.hpp"
#include "slicestation/pipeline/atlas_slicing.hpp"
#include "slicestation/pipeline/registration.hpp"

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include <array>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <optional>
#include <string>
#include <vector>

namespace slicestation::daemon {

/// The full map from section pixels to atlas pixels, as kept on disk: the affine (working px
/// -> atlas px) and the displacement field (atlas px) on nodes `cellPx` working px apart.
/// Section pixel p is working pixel w = (p + 0.5) workingScale - 0.5; atlas = A w + field(w),
/// the field bilinear between nodes (node (i, j) at w = (j cellPx, i cellPx)), clamped to the
/// outermost nodes outside the grid. Reproduces pipeline::Registration::atlasFromImage.
struct SavedMapping {
    cv::Size imageSize;
    double workingScale = 1;
    cv::Matx23d atlasFromWorking = cv::Matx23d::eye();
    double cellPx = 1;
    cv::Mat dx, dy; ///< CV_32F node values (atlas px); empty = no non-linear part

    cv::Matx23d affineAtlasFromImage() const;
    cv::Point2d atlasFromImage(cv::Point2d imagePx) const;
    /// Atlas coordinates of every pixel of an image of `size` (the section, or a copy scaled to
    /// `size`), CV_32F maps for cv::remap.
    void atlasMaps(cv::Size size, cv::Mat& mapX, cv::Mat& mapY) const;
};

SavedMapping savedMapping(const pipeline::Registration& registration);

/// Writes the field as a float32 TIFF of two pages (dx, then dy; atlas px; one sample per page,
/// the node grid's size). An empty field is written as one node of zero.
/// \return the errors of the file layer (IoError, NotFound for a missing directory).
[[nodiscard]] core::Result<void> writeMappingField(const std::filesystem::path& path,
                                                   const SavedMapping& mapping);

/// result.json's "mapping" object for `mapping` with its field in `fieldFile` (a name relative to
/// result.json's directory).
nlohmann::json mappingJson(const SavedMapping& mapping, const std::string& fieldFile);

/// The mapping of a result document (its "mapping" object and "image" size) with its field
/// read from `resultDir`. \return InvalidArgument (no or malformed "mapping": the message names
/// the field; results written before the mapping was kept have none), NotFound / IoError (the field
/// file), InvalidArgument (the field's pages differ in size or are not float32).
[[nodiscard]] core::Result<SavedMapping> readSavedMapping(const nlohmann::json& result,
                                                          const std::filesystem::path& resultDir);

/// Where a registered atlas slice lies: from the stack's manifest.
struct AtlasSliceFrame {
    int index = 0;
    double positionUm = 0;
    double umPerPx = 0;
    pipeline::SliceGeometry geometry;
    /// The stack was cut from a volume (kind "volume"): the atlas frame is CCFv3 micrometres.
    bool ccf = false;
    /// The atlas frame's left-right coordinate of the midline (the volume's centre).
    double midlineLrUm = 0;
    std::string stackDir; ///< as given (result.json holds it relative to its own directory)
    /// The slice's atlas intensity plane as the manifest names it (relative to stackDir), empty
    /// when the stack holds none: the registration service then gives it to the registration.
    std::string templateFile = {};
    /// The slice's plane of every atlas id (StackSlice::idsFile, relative to stackDir) and the
    /// stack's ventricle ids (AtlasStack::ventricleIds): the registration service gives them to
    /// the region warp. Empty when the stack holds none.
    std::string idsFile = {};
    std::vector<std::int32_t> ventricleIds = {};
};

AtlasSliceFrame sliceFrame(const AtlasStack& stack, int index);
nlohmann::json sliceFrameJson(const AtlasSliceFrame& frame);
/// \return InvalidArgument naming the missing or malformed field.
[[nodiscard]] core::Result<AtlasSliceFrame> sliceFrameFromJson(const nlohmann::json& j);

/// CCFv3 micrometres (x anterior-posterior, y dorsal-ventral, z left-right; Allen's axes, voxel
/// index x voxel size) of an atlas pixel of a slice of a CCF stack.
cv::Vec3d ccfUm(const pipeline::SliceGeometry& slice, cv::Point2d atlasPx);

/// QuickNII's 25 um voxel space (ABA_Mouse_CCFv3_2017_25um): x left->right, y
/// posterior->anterior, z inferior->superior, continuous with voxel i covering [i, i + 1).
inline constexpr const char* kQuickNiiTarget = "ABA_Mouse_CCFv3_2017_25um.cutlas";
inline constexpr int kQuickNiiSize[3] = {456, 528, 320};
cv::Vec3d quickNiiFromCcf(cv::Vec3d ccfUm);
cv::Vec3d ccfFromQuickNii(cv::Vec3d voxel);

struct QuickNiiOptions {
    /// VisuAlign markers on a staggered grid this many columns across the image (rows spaced
    /// alike); 0 = no markers (anchoring only).
    int markerColumns = 32;
};

/// One QuickNII/VisuAlign slice: filename, nr, width, height, anchoring (the affine part) and
/// markers ([x_src, y_src, x_dst, y_dst] in the slice's width x height space: VisuAlign maps a
/// point at dst to the anchoring's plane at src, piecewise linearly between markers).
nlohmann::json quickNiiSlice(const std::string& filename, int nr, const SavedMapping& mapping,
                             const pipeline::SliceGeometry& slice,
                             const QuickNiiOptions& options = {});
/// {"name", "target", "target-resolution", "slices"}.
nlohmann::json quickNiiSeries(const std::string& name, nlohmann::json slices);

/// Where QuickNII (markers ignored) or VisuAlign (markers used) puts section pixels of one
/// slice: QuickNII voxel coordinates. Delaunay triangulation of the markers' dst points and the
/// image corners (corners fixed), as VisuAlign does; built once, then any number of points.
class VisuAlignMap {
public:
    /// \return InvalidArgument for a malformed slice (size, anchoring, a marker not 4 numbers or
    /// outside the image).
    [[nodiscard]] static core::Result<VisuAlignMap> create(const nlohmann::json& slice,
                                                           bool useMarkers);
    /// Section pixel `imagePx` (centres at integers).
    cv::Vec3d voxelOf(cv::Point2d imagePx) const;

private:
    double width_ = 1, height_ = 1;
    std::array<double, 9> anchoring_{};
    std::vector<cv::Point2d> src_, dst_;
    std::vector<std::array<int, 3>> triangles_;
};
/// One point: VisuAlignMap::create(slice, useMarkers)->voxelOf(imagePx).
[[nodiscard]] core::Result<cv::Vec3d> quickNiiVoxelOf(const nlohmann::json& slice,
                                                      cv::Point2d imagePx, bool useMarkers);

/// Names, acronyms and colours of atlas ids.
using RegionLookup = std::function<const StackRegion*(std::uint32_t id)>;

/// QuPath GeoJSON: a FeatureCollection with one feature per (atlas region, hemisphere) present
/// in `labelsInImage` (CV_32S at section size) split by `side` (CV_8U, 1 = right; empty = no
/// hemispheres), polygons in QuPath's pixel coordinates; and one "Damage" feature per damage
/// polygon of `damageRegions` (result.json's "damage_regions").
nlohmann::json qupathFeatures(const cv::Mat& labelsInImage, const cv::Mat& side,
                              const RegionLookup& regions, const nlohmann::json& damageRegions);

/// A section's exports from its result document and the files beside it (`resultDir`): the
/// atlas slice (atlas.file), the stack manifest (atlas.stack.dir, for region names, unless the
/// document carries "regions"), the field (mapping.field).
struct SectionFiles {
    nlohmann::json result;
    std::filesystem::path resultDir;
};
/// \return InvalidArgument when the atlas slice is not from a CCF stack (no QuickNII space),
///         the errors of readSavedMapping and sliceFrameFromJson.
[[nodiscard]] core::Result<nlohmann::json>
quickNiiSliceOfResult(const SectionFiles& section, const std::string& filename, int nr,
                      const QuickNiiOptions& options = {});
/// \return the errors of readSavedMapping, sliceFrameFromJson, core::readImage (atlas slice).
[[nodiscard]] core::Result<nlohmann::json> qupathOfResult(const SectionFiles& section);

/// Reads result.json. \return NotFound, IoError, InvalidArgument (not a JSON object).
[[nodiscard]] core::Result<SectionFiles> readResultFile(const std::filesystem::path& resultJson);

} // namespace slicestation::daemon
