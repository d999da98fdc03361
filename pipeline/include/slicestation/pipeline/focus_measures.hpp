#pragma once
/// Measures of one camera field, for autofocus: sharpness and how much of it is tissue.
/// Threading: pure functions, re-entrant. Never throw (an OpenCV failure gives 0).
#include <opencv2/core.hpp>

namespace slicestation::pipeline {

double focusMeasure(const cv::Mat& image);

/// Share (0..1) of the field that is tissue. Works for fluorescence (bright tissue on dark
/// glass) and brightfield (dark tissue on bright glass): the glass level is the 2nd percentile
/// (dark field, median below half scale) or the 98th percentile (bright field); a pixel is
/// tissue when it differs from the glass by more than max(5 x noise, 2% of full scale), the
/// noise being estimated from neighbouring-pixel differences. Computed on a copy downscaled to
/// at most 256 px per side. Blank glass, in or out of focus, gives ~0. Empty image: 0.
double tissueFraction(const cv::Mat& image);

} // namespace slicestation::pipeline
