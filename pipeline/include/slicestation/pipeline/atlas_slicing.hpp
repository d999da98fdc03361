#pragma once
/// Virtual slicing of a 3-D label volume (paper section 3.2: the atlas is cut at the same angle
/// and interval as the real brain): one label image per cutting plane, nearest-neighbour so the
/// ids survive.
///
/// The atlas frame: micrometres along (AP, DV, LR) = (anterior->posterior, dorsal->ventral,
/// one side to the other), origin at the centre of the volume's first voxel, whatever the file's
/// axis order (VolumeAxes says how to read it). Pure computation, re-entrant.

#include "slicestation/core/nrrd.hpp"
#include "slicestation/core/result.hpp"
#include "slicestation/pipeline/atlas.hpp"

#include <opencv2/core.hpp>

#include <cstdint>
#include <functional>
#include <string_view>
#include <vector>

namespace slicestation::pipeline {

/// Which axis the untilted plane is normal to, and how its image is laid out:
/// - Coronal: normal AP; columns LR, rows DV (dorsal at the top).
/// - Sagittal: normal LR; columns AP (anterior on the left), rows DV (dorsal at the top).
/// - Horizontal: normal DV; columns LR, rows AP (anterior at the top).
enum class PlaneOrientation { Coronal, Sagittal, Horizontal };

std::string_view toString(PlaneOrientation orientation) noexcept;
/// "coronal", "sagittal" or "horizontal"; InvalidArgument otherwise.
[[nodiscard]] core::Result<PlaneOrientation> parsePlaneOrientation(std::string_view name);

/// One cutting plane. The plane turns about the point where the untilted normal through the
/// volume's centre meets it, so `positionUm` is where the plane crosses that line.
struct CuttingPlane {
    PlaneOrientation orientation = PlaneOrientation::Coronal;
    double positionUm = 0;     ///< along the untilted normal, atlas frame
    double tiltColumnsDeg = 0; ///< the normal leans toward the column axis (coronal: LR tilt)
    double tiltRowsDeg = 0;    ///< the normal leans toward the row axis (coronal: DV tilt)
    double umPerPx = 0;        ///< output pixel size, > 0
};

/// Where a slice image lies in the atlas frame (micrometres, (AP, DV, LR)).
struct SliceGeometry {
    cv::Size size;         ///< image size in pixels
    cv::Vec3d originUm;    ///< centre of pixel (0, 0)
    cv::Vec3d columnUm;    ///< one pixel step to the right
    cv::Vec3d rowUm;       ///< one pixel step down
    cv::Vec3d normal;      ///< unit normal, the tilted direction of increasing position
    double positionUm = 0; ///< as in CuttingPlane

    /// Atlas-frame point of a pixel (pixel centres at integers).
    cv::Vec3d atlasUm(double col, double row) const {
        return originUm + col * columnUm + row * rowUm;
    }
};

/// Volume size along the atlas axes (AP, DV, LR), micrometres from the first to the last voxel
/// centre.
cv::Vec3d volumeExtentUm(const core::Volume& volume, VolumeAxes axes);

/// Geometry of `plane` through `volume`. The image covers the volume's cross-section (widened by
/// 1/cos(tilt) so a tilted plane is not cropped); at umPerPx equal to the voxel size an untilted
/// plane's pixels are exactly the voxels of that plane.
/// \return InvalidArgument (umPerPx <= 0 or not finite, volume without spacing, tilt beyond 60
///         degrees), OutOfRange (position outside the volume along the normal).
[[nodiscard]] core::Result<SliceGeometry> planeGeometry(const core::Volume& volume, VolumeAxes axes,
                                                        const CuttingPlane& plane);

/// Labels along `geometry` by nearest neighbour (each pixel centre takes the voxel it falls
/// in), 0 outside the volume. CV_32S.
/// \return InvalidArgument when an id does not fit 31 bits.
[[nodiscard]] core::Result<cv::Mat> sampleLabels(const core::Volume& volume, VolumeAxes axes,
                                                 const SliceGeometry& geometry);

/// Where the atlas frame of `labels` (origin at the centre of its first voxel) lies in the frame
/// of `intensity`, another volume of the same space at another voxel size (e.g. the Allen average
/// template at 100 um beside a 25 um annotation): both start at the same corner, so the offset
/// is half a label voxel less half an intensity voxel per axis.
/// \return InvalidArgument (a volume without voxel size, or extents that differ by more than one
///         intensity voxel along an axis: not the same space; the message gives both).
[[nodiscard]] core::Result<cv::Vec3d> intensityFrameOffsetUm(const core::Volume& labels,
                                                             VolumeAxes labelAxes,
                                                             const core::Volume& intensity,
                                                             VolumeAxes intensityAxes);

/// Intensities of `volume` along `geometry` (a plane of the labels' frame; `offsetUm` from
/// intensityFrameOffsetUm), trilinear, divided by `scale` (> 0), 0 outside the volume. CV_32F.
cv::Mat sampleIntensity(const core::Volume& volume, VolumeAxes axes, const SliceGeometry& geometry,
                        const cv::Vec3d& offsetUm, double scale);

/// An evenly spaced cutting plan: planes from `firstUm` every `intervalUm` while inside the
/// volume along the normal.
struct CuttingPlan {
    PlaneOrientation orientation = PlaneOrientation::Coronal;
    double firstUm = 0;
    double intervalUm = 100;
    double tiltColumnsDeg = 0;
    double tiltRowsDeg = 0;
    double umPerPx = 25;
};

/// Budget of a cut stack, checked before any plane is sampled: at most kMaxStackSlices planes,
/// kMaxSlicePixels per plane and kMaxStackBytes of CV_32S labels in all. A 10 mm brain cut every
/// 10 um at 25 um/px (1000 planes of 456 x 320 px) takes 584 MB; 1 um/px planes of the whole
/// 25 um volume are 91 Mpx each.
inline constexpr int kMaxStackSlices = 10000;
inline constexpr std::int64_t kMaxSlicePixels = std::int64_t{1} << 27;
inline constexpr std::int64_t kMaxStackBytes = std::int64_t{2} << 30;

/// InvalidArgument when `slices` planes of `size` exceed the budget above; the message gives the
/// plan's size and the budget.
[[nodiscard]] core::Result<void> checkStackBudget(double slices, cv::Size size);

struct AtlasSlice {
    cv::Mat labels; ///< CV_32S
    SliceGeometry geometry;
    /// Optional intensity plane of the same pixels (CV_32F, e.g. the Allen average template):
    /// the registration's atlas intensity. Empty = none.
    cv::Mat intensity = {};
    /// Optional: every atlas id of the same pixels (CV_32S) when `labels` are collapsed (a
    /// major-region stack), for the registration's region warp, which fits every region the
    /// section's stain shows. Empty = `labels` hold the ids as the volume has them.
    cv::Mat ids = {};
};

/// Called after each plane is cut: (planes done, planes in the plan).
using SliceProgress = std::function<void(int done, int total)>;

/// Every plane of `plan`; `progress`, when set, after each plane. \return as planeGeometry
///         (OutOfRange when firstUm lies outside), InvalidArgument for intervalUm <= 0 or a plan
///         beyond the stack budget (checkStackBudget), before anything is sampled.
[[nodiscard]] core::Result<std::vector<AtlasSlice>> sliceVolume(const core::Volume& volume,
                                                                VolumeAxes axes,
                                                                const CuttingPlan& plan,
                                                                const SliceProgress& progress = {});

} // namespace slicestation::pipeline
