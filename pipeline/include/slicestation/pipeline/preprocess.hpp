#pragma once
/// Turning a captured section into the working image the registration uses.

#include "slicestation/core/result.hpp"

#include <opencv2/core.hpp>

namespace slicestation::pipeline {

/// How the glass looks: fluorescence has dark glass, brightfield bright glass.
enum class Contrast { Fluorescence, Brightfield };

struct PreparedSection {
    cv::Mat grey; ///< CV_32F in [0,1], tissue bright whatever the stain, working resolution
    /// `grey` before it is clipped to [0,1]: the same scale (0 and 1 are the image's 0.5% and
    /// 99.5% levels), the same orientation and flattening, but the brightest tissue keeps what
    /// the camera measured above the 99.5% level. For measures of how much tissue lies at a
    /// place (a fold doubles it), which the clipping would cap at the image's brightest 0.5%.
    cv::Mat level;
    cv::Mat tissueMask; ///< CV_8U, 255 on tissue (holes such as ventricles and tears stay 0)
    /// For damage: all that is clearly above the glass (dark tissue too, the outline slightly
    /// wider), unclosed and barely blurred so thin cracks stay open.
    cv::Mat tissueMaskFine;
    /// The fine mask's pieces left out of tissueMask as debris (under 2% of the largest piece):
    /// dust, or a small lobe cut apart from the rest (a paraflocculus) that the atlas expects,
    /// which damage detection must not take for missing tissue.
    cv::Mat smallPiecesFine;
    double scale = 1.0; ///< working pixels per full-resolution pixel (<= 1)
    Contrast contrast = Contrast::Fluorescence;
};

/// prepareSection keeps tissue pieces of at least 2% of the largest one, and solid pieces down
/// to kMinFragmentShare of it whose inscribed radius reaches kMinFragmentRadius of the largest
/// one's equivalent radius and that lie whole inside the image: detached fragments of the
/// section, which the damage check reports (extraPieces with the same share). Smaller or thin
/// pieces are debris.
inline constexpr double kMinFragmentShare = 0.005;
inline constexpr double kMinFragmentRadius = 0.03;

/// Converts any supported image (CV_8U/16U/32S/32F; 1 channel grey, 2 channels = channel 0 is the
/// tissue stain, 3/4 channels BGR(A) = luminance) into a normalised grey working image whose
/// longer side is at most `workingMaxSide`, tells fluorescence from brightfield by the glass
/// around the tissue, and segments the tissue.
/// \return InvalidArgument (empty image, unsupported type, side < 32 px), NoTissue (blank
///         image, or tissue covering almost all or almost none of it).
[[nodiscard]] core::Result<PreparedSection> prepareSection(const cv::Mat& image,
                                                           int workingMaxSide);

/// Grey float copy of `image` (same size), channel rules as above, not normalised.
[[nodiscard]] core::Result<cv::Mat> toGreyFloat(const cv::Mat& image);

} // namespace slicestation::pipeline
