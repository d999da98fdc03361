#pragma once
/// Registering one section image to one atlas label image, with typed results: what the
/// registration worker (and `slicectl register`) call. Reads both images, checks them,
/// registers (pipeline::registerSection), and writes every requested output atomically: the
/// result document (RESULT.json, docs/operation.md), the overlay PNG and the atlas labels in the
/// section frame (CV_32S TIFF); always the full mapping's displacement field beside RESULT.json
/// (`<RESULT stem>.field.tif`, docs/results.md).
///
/// Threading: re-entrant; blocking file I/O and a registration of about a second.
#include "slicestation/core/result.hpp"
#include "slicestation/daemon/export/section_export.hpp"
#include "slicestation/daemon/storage/atlas_stack.hpp"
#include "slicestation/pipeline/registration.hpp"

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include <filesystem>
#include <functional>
#include <optional>
#include <vector>

namespace slicestation::daemon {

/// Pixel sizes a request may give (micrometres per pixel): from a 100x objective to a
/// 1 mm-per-pixel thumbnail.
inline constexpr double kMinUmPerPx = 0.01;
inline constexpr double kMaxUmPerPx = 1000;
/// Section images registered: 300 to 8000 px on each side (README). Smaller holds too little
/// tissue to find edges in; larger is a tiled scan to be reduced before registration.
inline constexpr int kMinSectionSidePx = 300;
inline constexpr int kMaxSectionSidePx = 8000;

struct RegisterRequest {
    std::filesystem::path atlas; ///< label image (8/16/32-bit ids or colour-coded RGB)
    /// The atlas's intensity plane (e.g. the Allen average template cut like the labels): a
    /// one-channel float32, 8- or 16-bit image of the labels' size, given to the registration
    /// as its atlas intensity. Without it, a stack slice's own template plane (atlasSlice) is.
    std::optional<std::filesystem::path> atlasTemplate;
    std::filesystem::path image;                       ///< section image (PNG or TIFF)
    std::optional<std::filesystem::path> points;       ///< CSV x,y to map (read by loadPoints)
    std::filesystem::path output;                      ///< RESULT.json
    std::optional<std::filesystem::path> overlay;      ///< PNG
    std::optional<std::filesystem::path> warpedLabels; ///< TIFF, CV_32S ids at section size
    double imageUmPerPx = 0;                           ///< 0 = unknown
    double atlasUmPerPx = 0;                           ///< 0 = unknown
    int workingMaxSide = 1024;
    /// The lab's mounting rule: sections are turned at most this far on the slide (degrees;
    /// 180 = any way). See pipeline::RegistrationOptions::maxTurnDeg.
    double maxTurnDeg = 180;
    /// The atlas is this slice of a stack: result.json then records the slice (index, position,
    /// frame) and, for a stack cut from a CCF volume, every point's "ccf_um".
    std::optional<AtlasSliceFrame> atlasSlice;
    /// The regions of the stack `atlasSlice` is cut from, with their ontology paths. When the
    /// labels hold ids below the paper's major regions (a stack sliced `--regions all`) and every
    /// id has its path, the registration gets the labels collapsed to the major regions (its
    /// edges, outline and damage check are made for them) and paints every id in its region warp
    /// (pipeline::RegistrationOptions::regionLabels); results, overlays and warped labels keep
    /// every id. Empty, or a stack of major regions: the labels are registered as they are.
    std::vector<StackRegion> stackRegions;
    /// The plane of every atlas id when `atlas` holds them collapsed to the major regions (a
    /// uint32 label image of the labels' size; e.g. a tilted plane cut from a major-region
    /// stack's volume). Without it, a stack slice's own id plane (atlasSlice->idsFile) is. The
    /// region warp paints these ids (the ventricles among them, atlasSlice->ventricleIds, as
    /// glass); results keep the labels of `atlas`.
    std::optional<std::filesystem::path> atlasIds;
    /// The region warp (above); off: every-id labels are still collapsed for the registration.
    bool regionWarp = true;
    /// Registration steps done of steps total (pipeline::RegistrationOptions::progress), for
    /// slicectl's bar. May be empty.
    std::function<void(int done, int total)> progress;
};

/// A section registered, typed; `document` is what was written to RESULT.json.
struct RegisteredSection {
    pipeline::Registration registration;
    cv::Size sectionSize;
    cv::Mat warpedLabels; ///< CV_32S atlas ids at section size; empty unless requested
    nlohmann::json document;
};

/// Checks: pixel sizes 0 (unknown) or finite within [kMinUmPerPx, kMaxUmPerPx] (both or
/// neither); the section kMinSectionSidePx..kMaxSectionSidePx on each side; the atlas labels
/// holding both brain (non-zero ids) and outside (0).
/// \return the first error met: NotFound / IoError for files, InvalidArgument for malformed
///         input (the message names the file and what is wrong), NoTissue. Nothing is written
///         then.
/// Reads the points file of a request (slicectl's CSV reader); called after both images are read.
using PointsLoader =
    std::function<core::Result<std::vector<cv::Point2d>>(const std::filesystem::path&)>;
[[nodiscard]] core::Result<RegisteredSection>
registerSectionFiles(const RegisterRequest& request, const PointsLoader& loadPoints = {});

} // namespace slicestation::daemon
