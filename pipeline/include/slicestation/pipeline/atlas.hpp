#pragma once
/// Atlas label planes: from label images and 3-D volumes, and collapsing Allen ids into the
/// paper's major regions.

#include "slicestation/core/nrrd.hpp"
#include "slicestation/core/ontology.hpp"
#include "slicestation/core/result.hpp"

#include <opencv2/core.hpp>

#include <cstdint>
#include <set>
#include <vector>

namespace slicestation::pipeline {

/// A label image as the pipeline wants it: CV_32S, 0 outside the brain.
/// Accepts 8/16-bit or 32-bit integer single-channel images (ids as stored) and colour-coded
/// 3/4-channel 8-bit images (one colour per region; the colour is packed as 0xRRGGBB and the
/// colour that dominates the image border is outside = 0).
/// \return InvalidArgument: empty, float or multi-channel non-colour image, or no label at all.
[[nodiscard]] core::Result<cv::Mat> labelsFromImage(const cv::Mat& image);

/// Axis conventions of 3-D atlas volumes (see ../shared/atlas/allen-ccf-2017/README.md).
enum class VolumeAxes {
    Allen,   ///< axis 0 anterior->posterior, 1 dorsal->ventral, 2 left->right
    QuickNii ///< axis 0 left->right, 1 posterior->anterior, 2 inferior->superior
};

/// The coronal plane at anterior-posterior voxel index `apIndex` (counted from the front, in the
/// volume's own spacing) as an image with dorsal at the top: rows DV, columns LR.
/// \return OutOfRange when apIndex lies outside the volume, InvalidArgument for ids > INT32_MAX.
[[nodiscard]] core::Result<cv::Mat> coronalPlane(const core::Volume& volume, VolumeAxes axes,
                                                 int apIndex);

/// The paper's 20 major regions (Table 2), then fibre tracts (1009) and ventricles (73).
const std::vector<std::uint32_t>& majorRegionIds();

/// Where collapseLabels to majorRegionIds puts the voxels no major region claims: Allen's "Basic
/// cell groups and regions" (8), so the brain keeps its outline (`atlas slice --regions major`).
inline constexpr std::int32_t kOtherRegionId = 8;
/// Allen's "ventricular systems" (one of majorRegionIds): its ids are glass in a section.
inline constexpr std::uint32_t kVentricularSystemsId = 73;

/// Adds the ids of `labels` (CV_32S; 0, outside the brain, left out) to `ids`.
void collectIds(const cv::Mat& labels, std::set<std::int32_t>& ids);

/// The ids of `ids` that are `ancestorId` or lie below it in `ontology`, in increasing order.
std::vector<std::int32_t> idsUnder(const std::set<std::int32_t>& ids,
                                   const core::Ontology& ontology, std::uint32_t ancestorId);

/// Replaces every id by its deepest ancestor-or-self among `regionIds` (so Epithalamus stays
/// itself inside Thalamus); ids with no such ancestor become `otherId` (0 drops them).
cv::Mat collapseLabels(const cv::Mat& labels, const core::Ontology& ontology,
                       const std::vector<std::uint32_t>& regionIds, std::int32_t otherId);

} // namespace slicestation::pipeline
